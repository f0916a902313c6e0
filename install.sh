#!/usr/bin/env bash
# Installs attitude-bridge with its test tools, the report extra (bokeh, matplotlib)
# and the cluster extra (dask.distributed, for `replay`/`tune --scheduler`)
# into the current Python environment (editable), plus mosquitto, zstd and chromium (for
# the integration tests' MQTT broker, real autopilots and the web view's browser tests)
# from Debian when root; then compiles the estimators ahead
# (`attitude-bridge warmup`) and smoke-tests the install. The Python part is
# docker/setup.sh, the same script the Docker image is built with.
set -euo pipefail
cd "$(dirname "$0")"
# Debian packages: mosquitto (the MQTT tests start their own broker), zstd (the real
# PX4 / ArduPilot SITL runtimes in ../shared/autopilots are zstd-packed tarballs) and
# chromium (the web view's tests drive it; users of the view bring their own browser).
missing=()
command -v mosquitto >/dev/null 2>&1 || [ -x /usr/sbin/mosquitto ] || missing+=(mosquitto)
command -v zstd >/dev/null 2>&1 || missing+=(zstd)
command -v chromium >/dev/null 2>&1 || missing+=(chromium)
if [ ${#missing[@]} -gt 0 ]; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
        apt-get update -qq
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
        # The package may start a system broker on 1883; the tests start their own.
        (service mosquitto stop || true) >/dev/null 2>&1
    else
        echo "install.sh: ${missing[*]} not found; install (e.g. apt-get install ${missing[*]})" >&2
    fi
fi
python -m pip install -q --upgrade pip
bash docker/setup.sh -e . "test,report,cluster,compare"
