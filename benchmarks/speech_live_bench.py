"""Benchmark of `geoavatar speak --microphone --view`: a live sound drives the avatar in the browser player.

Our machines have no microphone, so the sound is a file played as a live source, two ways:
    file        the file played in real time in Python (`speak --audio FILE --live --view`: RealTimeSound, 20 ms
                chunks at the sound's own pace)
    microphone  the browser's microphone path itself: headless Chromium's fake capture device plays the file
                (`--use-file-for-fake-audio-capture`), the page resamples it to 16 kHz in its AudioWorklet and sends
                20 ms chunks over the websocket (`speak --microphone --view`)
In both, a headless Chromium page (software WebGL, at nice 10 so that it does not take the pipeline's core) draws the
meshes. Reported: the frames made per second (after the first), frames dropped, the server's sound-to-mesh latency
(from the capture of a frame's own instant of sound to its mesh sent: the look-ahead, the 20 ms chunking, the voice
model, the posing, the send; p50 / p95) and the page's sound-to-picture latency (the same instant to the frame handed
to WebGL). The load average is printed before and after.

    .venv/bin/python benchmarks/speech_live_bench.py RUN SOUND [--seconds 20] [--paths file microphone]
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from pathlib import Path

import numpy as np


def load() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def percentiles(values) -> dict:
    values = np.asarray(values, np.float64)
    if values.size == 0:
        return {"p50": None, "p95": None, "count": 0}
    return {"p50": round(float(np.percentile(values, 50)), 1), "p95": round(float(np.percentile(values, 95)), 1),
            "count": int(values.size)}


def measure(run, voice, sound, path: str, seconds: float, wav: Path, page_size: int = 512) -> dict:
    """One live pass of `seconds` of sound through the pipeline into a Chromium page."""
    from geoavatar.animation.sources.speech import MicrophoneSound, RealTimeSound
    from geoavatar.apps.speak import speak_live
    from geoavatar.apps.view import start_viewer
    from geoavatar.web.browser import chromium_page, fake_microphone

    if path == "microphone":
        sound_input = MicrophoneSound()
        viewer = start_viewer(run, port=0, expr_sliders=0, live="speak", on_audio=sound_input.on_audio,
                              on_microphone_error=sound_input.on_error)
        flags = fake_microphone(wav)
    else:
        sound_input = RealTimeSound(sound)
        viewer = start_viewer(run, port=0, expr_sliders=0, live=True)
        flags = []
    result: dict = {}

    def work():
        try:
            result["source"] = speak_live(run, voice, sound_input, 25.0, 0, viewer, max_seconds=seconds, status=False)
        except BaseException as err:  # reported below, in the main thread
            result["error"] = err

    try:
        with chromium_page(page_size, page_size, nice=10, args=flags) as page:
            page.goto(viewer.url)
            page.wait_for_function("window.geoavatar && window.geoavatar.stats.ready", timeout=120_000)
            thread = threading.Thread(target=work, daemon=True)
            thread.start()
            thread.join(timeout=seconds * 4 + 60)
            time.sleep(1.0)
            page_stats = page.evaluate("window.geoavatar.stats")
    finally:
        viewer.stop()
    if "source" not in result:
        raise RuntimeError(f"the {path} pass did not finish: {result.get('error', 'timed out')!r}")
    stats = result["source"].stats
    return {"path": path, "page_size": page_size, "frames": stats.frames, "fps": round(stats.fps, 2),
            "dropped": stats.dropped,
            "made": stats.delivered, "sound_to_mesh_ms": percentiles(stats.latency_ms),
            "sound_to_picture_ms": percentiles(page_stats.get("soundToPictureMs", [])),
            "page_drawn": page_stats.get("drawn"), "page_received": page_stats.get("received"),
            "stage_ms": {k: round(float(np.mean(v)), 2) for k, v in stats.stage_ms.items() if v}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("sound", type=Path, help="a sound or video file (played as the live source)")
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--paths", nargs="+", default=["file", "microphone"], choices=["file", "microphone"])
    parser.add_argument("--page-size", type=int, default=512, help="the page's viewport (software GL draws slowly)")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()

    from geoavatar.runtime import setup_process

    setup_process()
    import torch

    from geoavatar.sound import RATE, read_sound, write_wav
    from geoavatar.train.checkpoint import open_run
    from geoavatar.voice import VoiceModel

    torch.set_num_threads(1)
    run = open_run(args.run, "cpu")
    voice = VoiceModel.load(args.run)
    sound = read_sound(args.sound, RATE).segment(0.0, args.seconds + 1.0)
    wav = write_wav(Path("/tmp") / "speech_live_bench.wav", sound)
    print(f"load average before: {load()}; {run.avatar.num_gaussians} Gaussians; look-ahead {voice.config.ahead} s")
    results = [measure(run, voice, sound, path, args.seconds, wav, args.page_size) for path in args.paths]
    for r in results:
        print(json.dumps(r))
    print(f"load average after: {load()}")
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
