#!/usr/bin/env bash
# Device-side: bash benchmarks/gpu_runs/run23/viewer.sh, from the repository root with .gpu/ carried (the kit of
# ../shared/gpu/prepare.sh, whose wheels now hold viser 1.1.1 and what it imports); outputs under $OUT/viewer/.
# The viewer's server path (issue 29): frames/s that a scripted websocket client receives at 1280 x 720 from an
# unfitted `paper` avatar of 100k splats while the demo motion plays and the camera orbits (target >= 30), the
# server's parts per frame, and the last frame received (frame_gpu.jpg). benchmarks/viewer_stream.py says how.
# Expected GPU wall time: ~1.5 min (kit install 60-90 s on a fresh machine, none on a warm one; avatar build and
# the finest level's compile + graph capture ~20-40 s; 3 s warm-up, 10 s of counting, 30 frames of parts).
set -u
[ -d /tmp/site/gsplat ] && [ -d /tmp/site/viser ] && [ -d /tmp/text ] || bash .gpu/device-setup.sh >/dev/null
export PYTHONPATH=/tmp/site:$PWD TORCH_EXTENSIONS_DIR=/tmp/text PYTHONUNBUFFERED=1
mkdir -p "$OUT/viewer"
python3 -c "import viser, websockets, msgspec, zstandard; print('viser', viser.__version__, 'websockets', websockets.__version__)" \
  2>&1 | tee "$OUT/viewer/setup.txt"
# viser's banner is box drawing: left out of the log.
timeout 300 python3 benchmarks/viewer_stream.py --device cuda --json "$OUT/viewer/stream.json" \
  --frame "$OUT/viewer/frame_gpu.jpg" 2>&1 | grep -v '[│╭╰]' | tee "$OUT/viewer/stream.txt"
nvidia-smi --query-gpu=name,memory.used --format=csv,noheader | tee -a "$OUT/viewer/stream.txt"
