#!/usr/bin/env bash
# Install attitude-bridge into the current Python environment, compile its estimators
# and check that it runs: the Docker image's install step (docker/Dockerfile) and the
# development install's (install.sh, which CI runs), so every step here runs in CI.
#
#   docker/setup.sh [-e] SOURCE [EXTRAS]
#     SOURCE  a directory with pyproject.toml, or a wheel file
#     -e      editable install (development checkout)
#     EXTRAS  comma-separated optional extras, e.g. "report" or "test,report"
set -euo pipefail

editable=()
if [ "${1:-}" = "-e" ]; then
    editable=(-e)
    shift
fi
source="${1:?usage: setup.sh [-e] SOURCE [EXTRAS]}"
extras="${2:-}"
python="${PYTHON:-python}"
target="$source"
if [ -n "$extras" ]; then
    target="$source[$extras]"
fi

echo "setup: installing attitude-bridge from $target" >&2
"$python" -m pip install --no-cache-dir -q "${editable[@]}" "$target"
attitude-bridge --version

# numba compiles each estimator on first use; do it now, into NUMBA_CACHE_DIR (or next
# to the package), so that the first run starts in seconds.
attitude-bridge warmup

# Smoke test of what was installed: the bridge on its built-in emulator for a few
# seconds, with the status file the container HEALTHCHECK reads, must report healthy
# with IMU data flowing. Runs without any ATTITUDE_BRIDGE_* setting of the caller.
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
(
    for var in $(compgen -e | grep '^ATTITUDE_BRIDGE_' || true); do unset "$var"; done
    attitude-bridge run --duration 6 --estimator quaternion --status-file "$work/status.json" \
        -q > "$work/run.log" 2>&1 &
    bridge=$!
    healthy=""
    for _ in $(seq 1 50); do
        sleep 0.2
        if attitude-bridge health --status-file "$work/status.json" --need-input \
                > "$work/health.log" 2>&1; then
            healthy=yes
            break
        fi
    done
    status=0
    wait "$bridge" || status=$?
    if [ -z "$healthy" ] || [ "$status" != 0 ]; then
        echo "setup: smoke test failed (bridge exit $status)" >&2
        cat "$work/run.log" "$work/health.log" >&2
        exit 1
    fi
    echo "setup: smoke test passed: $(cat "$work/health.log")" >&2
)
