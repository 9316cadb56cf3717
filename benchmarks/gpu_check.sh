#!/bin/bash
# The GPU check, as one short script for a borrowed CUDA machine that reaches no package index (about 9 minutes on
# an H100): gsplat's build, the renderer's parity with gsplat, the training step on gsplat against the torch backend,
# the user's path on CUDA (train, track --avatar, eval, render) with its timings, the trained avatar's render frame
# rate at 512 and 1080 px, then the test suite with the time that is left. Logs go to
# $OUT (default /tmp/gpu_check). BENCHMARKS.md, "On a GPU", has its first figures.
#
# That machine already has CUDA's compiler, PyTorch, numpy, scipy, pytest(-xdist, -timeout); the project's other
# dependencies travel as wheels, downloaded here once into .whl/ (git-ignored; set PY to the machine's Python):
#
#   PY=3.12; for p in gsplat==1.5.3 tyro==0.9.35 docstring-parser shtab typeguard av==16.0.1 plyfile==1.0.3 \
#       websockets==16.1.1; do pip download -q --no-deps --only-binary=:all: --python-version $PY \
#       --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux2014_x86_64 -d .whl $p; done
#   bash benchmarks/gpu_check.sh            # on the GPU machine, from the repository root
#
# Not covered: mediapipe (prepare's landmarks; its tests fail there), the face metrics' weights (eval runs with
# --no-faces) and a browser (the web player's hardware-WebGL frame rate: web_player_bench.py gpu-fps).
set -u
export PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/gpu_check}
BUDGET=${BUDGET:-540}  # seconds this script may take in all; the suite gets what the steps before it leave
mkdir -p "$OUT"
T0=$(date +%s)
stamp() { echo "[$(($(date +%s) - T0)) s] $*"; }

{
  stamp start
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
  python3 -c "import torch, numpy; print('torch', torch.__version__, 'CUDA', torch.version.cuda, 'numpy', numpy.__version__)"
  if [ -d .whl ]; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/gpu_site .whl/*.whl
  fi
  stamp wheels installed
} > "$OUT/setup.log" 2>&1
export PYTHONPATH=/tmp/gpu_site:$PWD
# gsplat's kernels for this GPU only, on every core; kept in the checkout between calls on a warm machine
export TORCH_EXTENSIONS_DIR=${TORCH_EXTENSIONS_DIR:-$PWD/.gpu_ext/torch} GEOAVATAR_EXT_CACHE=${GEOAVATAR_EXT_CACHE:-$PWD/.gpu_ext/native}
export MAX_JOBS=${MAX_JOBS:-$(nproc)}
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-$(python3 -c "import torch; print('%d.%d' % torch.cuda.get_device_capability())")}
{ stamp "gsplat build (arch $TORCH_CUDA_ARCH_LIST)"; python3 -c "from gsplat.cuda._backend import _C"; stamp built; } >> "$OUT/setup.log" 2>&1

{ stamp parity; timeout 120 python3 -m pytest -q -p no:cacheprovider -rs tests/test_rasterize.py tests/test_rasterize_cpu.py
  stamp done; } > "$OUT/parity.log" 2>&1

{ stamp train_bench; timeout 90 python3 benchmarks/train_bench.py --device cuda --backends gsplat torch --presets E \
    --resolution 512 --frames 12 --steps 30 --warmup 5; stamp done; } > "$OUT/train_bench.log" 2>&1

W=/tmp/gpu_check_path
{
  stamp "the user's path on CUDA (the demo's subject and budget)"
  G="python3 -m geoavatar.cli"
  timeout 60 $G synth --out $W/subject --subject 0 --frames 160 --size 256 --no-progress && stamp synth &&
  timeout 120 $G train --data $W/subject --out $W/run --preset E --steps 1500 --resolution 128 --no-progress && stamp train &&
  timeout 90 $G track $W/subject --avatar $W/run --out $W/tracked --no-progress && stamp track &&
  timeout 60 $G eval $W/run --data $W/tracked --no-faces --no-floaters --no-progress && stamp eval &&
  timeout 60 $G render $W/run --split test --data $W/tracked --resolution 256 --no-progress && stamp render
} > "$OUT/user_path.log" 2>&1

# Render frame rate of the trained avatar (posing + rasterizing a new frame's parameters, #40) against the paper's
# 71.5 FPS on an RTX 3090 (512 x 512): the square dataset camera at 512 and at 1080 px.
{ for R in 512 1080; do stamp "bench at $R px"; timeout 60 python3 -m geoavatar.cli bench $W/run --resolution $R \
    --iterations 100 --warmup 10 --out "$OUT/bench_$R.json" --no-progress; done; stamp done; } > "$OUT/render_fps.log" 2>&1

LEFT=$((BUDGET - ($(date +%s) - T0)))
{ stamp "suite, $LEFT s left"; timeout "$LEFT" python3 -m pytest -q -p no:cacheprovider -n "$(nproc)" --timeout 300 \
    -rfE tests; stamp done; } > "$OUT/suite.log" 2>&1
stamp finished
