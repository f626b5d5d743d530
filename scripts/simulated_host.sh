#!/usr/bin/env bash
# Runs one process of a swarm and its mac-bridge as a simulated host: in a mount namespace of
# their own with a private /dev/shm and a private iceoryx2 root (/tmp/iceoryx2), so no shared
# memory can be shared with another simulated host; the host's only way out is the bridge's
# zenoh connection. Needs root (unshare --mount).
#
#   scripts/simulated_host.sh BRIDGE_BINARY [BRIDGE_ARGS...] -- PROGRAM [ARGS...]
#
# The bridge starts first; PROGRAM runs in the foreground of this script, and SIGTERM/SIGINT
# sent to the script go to PROGRAM (so a launcher stops it as it would stop the process
# itself). A bridge that dies (killed, crashed) is started again after BRIDGE_RESTART_S, as a
# service manager would on a real host; the bridges re-send what the far side had not
# acknowledged. When PROGRAM ends, the bridge is stopped (it writes its report) and the script
# exits with PROGRAM's status.
set -euo pipefail
if [[ "${MAC_SIMULATED_HOST_INSIDE:-}" != 1 ]]; then
  (($(id -u) == 0)) || { echo "[host] simulated hosts need root (unshare --mount)" >&2; exit 2; }
  export MAC_SIMULATED_HOST_INSIDE=1
  exec unshare --mount --propagation private bash "$0" "$@"
fi
mount -t tmpfs -o mode=1777 tmpfs /dev/shm
mkdir -p /tmp/iceoryx2
mount -t tmpfs -o mode=1777 tmpfs /tmp/iceoryx2

bridge=()
while (($#)) && [[ "$1" != -- ]]; do bridge+=("$1"); shift; done
(($#)) || { echo "[host] usage: simulated_host.sh BRIDGE [ARGS...] -- PROGRAM [ARGS...]" >&2; exit 2; }
shift
BRIDGE_RESTART_S=1
# The bridge's supervisor: SIGTERM stops the current bridge (in order) and the supervisor.
(
  trap 'kill -TERM "$child" 2>/dev/null; wait "$child"; exit $?' TERM
  while :; do
    "${bridge[@]}" &
    child=$!
    # Watches the bridge and this script ($$; once it is gone, killed, nobody needs the bridge).
    while kill -0 "$child" 2>/dev/null && kill -0 $$ 2>/dev/null; do sleep 0.5; done
    kill -0 $$ 2>/dev/null || { kill -TERM "$child" 2>/dev/null; wait "$child"; exit; }
    status=0
    wait "$child" || status=$?
    echo "[host] the bridge exited with status $status: starting it again in ${BRIDGE_RESTART_S} s" >&2
    sleep "$BRIDGE_RESTART_S"
  done
) &
bridge_pid=$!
"$@" &
main_pid=$!
trap 'kill -TERM "$main_pid" 2>/dev/null || true' TERM
trap 'kill -INT "$main_pid" 2>/dev/null || true' INT
# A trapped signal ends `wait` early: wait again until PROGRAM has really ended.
while :; do
  status=0
  wait "$main_pid" || status=$?
  kill -0 "$main_pid" 2>/dev/null || break
done
kill -TERM "$bridge_pid" 2>/dev/null || true
bridge_status=0
wait "$bridge_pid" || bridge_status=$?
((bridge_status == 0)) || echo "[host] the bridge exited with status $bridge_status" >&2
exit "$status"
