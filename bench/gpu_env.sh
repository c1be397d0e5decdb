# Sourced by bench/gpu_check.sh and bench/gpu_train.sh on a lent GPU machine: installs the
# carried GL libraries (.gl) and wheels (.whl, from bench/gpu_prepare.sh) and rainbench itself
# into /tmp/site, and sets the environment. GPU_CHECK_INSTALL=0 skips the installs (a local try
# with GPU_CHECK_PYTHON=.venv/bin/python).
python=${GPU_CHECK_PYTHON:-python3}
if [[ ${GPU_CHECK_INSTALL:-1} == 1 ]]; then
    for deb in .gl/*.deb; do dpkg -x "$deb" /; done
    ldconfig
    "$python" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/site .whl/*.whl || { echo "gpu_env: installing .whl failed"; exit 1; }
    "$python" -m pip install -q --no-index --no-deps --no-build-isolation --no-compile \
        --no-cache-dir --target /tmp/site . || { echo "gpu_env: installing rainbench failed"; exit 1; }
    # polars (54 MB) does not travel: a stand-in for the one call the trainer makes
    export PYTHONPATH=/tmp/site:$PWD/bench/gpu_polars
fi
export MUJOCO_GL=egl YOLO_OFFLINE=1 PYTHONUNBUFFERED=1
