#!/bin/bash
# One prepared GPU check (issue 48), for a session lent a GPU machine (it is not CI): bench inference
# on cuda (2 and 16 CPU threads) and on the same machine's CPU, and the validation scores on both
# devices. Each step under its own timeout, so one failure leaves the rest. Measured 2026-12-04 on an
# H200 (docs/inference-cuda.md): ~4 min after the machine's start.
#
# That machine has torch, numpy, OpenCV and matplotlib but not our other packages, and no internet;
# prepare here, in the repository's root (both folders ignored through .git/info/exclude):
#   .whl/  wheels for CPython 3.12 (pip download --no-deps --only-binary=:all: --python-version 3.12
#          --platform manylinux2014_x86_64 ...): kornia, kornia_rs, plyfile, moderngl, glcontext
#   .gl/   the GL loader packages (apt-get download libegl1 libglvnd0 libopengl0 libgl1 libglx0
#          libgles2 libvulkan1) for the procedural pairs through NVIDIA's EGL, and .gl/pairs/: a real
#          pair (drivingscene import ddad ... -o .gl/pairs/ddad02_0-2.npz) and one procedural pair
#          (drivingscene synth --seed 200000 -o .gl/pairs/procedural_200000.npz) for when EGL fails
# then: cp .ci/gpu-check.sh .gl/run.sh, and run `bash .gl/run.sh` there carrying .gl and .whl.
cd "$(dirname "$0")/.."
for f in .gl/*.deb; do dpkg -x $f / ; done; ldconfig
export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 DRIVINGSCENE_PROGRESS_AFTER=1000
DS="python3 -m drivingscene"
step() { local t=$1; shift; echo "=== $* ($(date +%T))"; timeout $t "$@" 2>&1 | grep -v Warning | tail -40; echo "=== rc ${PIPESTATUS[0]} ($(date +%T))"; }
nvidia-smi -L; lscpu | grep -E "Model name|^CPU\(s\)"
python3 -c "import torch,cv2,numpy,kornia;print('torch',torch.__version__,torch.cuda.is_available(),'cv2',cv2.__version__,'numpy',numpy.__version__)"
step 120 python3 -c "import time;t=time.time();from drivingscene.kernels import load_extension;print('kernels',load_extension(),round(time.time()-t,1),'s')"
step 60 $DS reconstruct .gl/pairs/procedural_200000.npz -o /tmp/r.npz --device cuda
[ -f /tmp/r.npz ] || exit 3
step 90 $DS synth --split val --count 6 -o /tmp/val176 --no-progress
S="--scenes .gl/pairs/ddad02_0-2.npz"; Z="176x320 352x640"; [ -f /tmp/val176/pair_100000.npz ] || { Z=""; S="$S .gl/pairs/procedural_200000.npz"; }
step 200 $DS bench inference --device cuda --sizes $Z $S --runs 5 -o $OUT/inference-cuda.md
step 100 $DS bench inference --device cuda --threads 16 --sizes 176x320 --runs 5 -o $OUT/inference-cuda-t16.md
D=/tmp/val176; [ -f $D/pair_100000.npz ] || D=.gl/pairs/procedural_200000.npz
step 100 $DS bench choices --data $D --count 6 --variant '' --device cuda -o $OUT/choices-cuda.md
step 100 $DS bench choices --data $D --count 6 --variant '' -o $OUT/choices-cpu.md
step 150 $DS bench inference --device cpu --threads 2 --sizes $Z $S --runs 5 -o $OUT/inference-cpu2.md
