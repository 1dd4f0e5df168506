#!/usr/bin/env bash
# Two "machines" on one box, to check the scaling model of docs/benchmarks.md:
#
#   machine A, this network namespace: `swimm router` and `swimm learn` (the SPEC's SAC, trained on from the
#     shipped policy, so episodes run their full length as in steady state);
#   machine B, network namespace swimm-b behind a veth link: SIMS x `swimm sim` and one `swimm encoder`, their
#     CPU limited to B_CORES cores by a cgroup (v1 cpu controller) when B_CORES is set.
#
# Every message between the machines crosses the veth link, as it would cross a LAN (netem delays, where the
# kernel has them, can be added to swimm-a and swimm-b0 by hand). Prints the learner's result.json (env-steps/s
# over the whole run). Needs root.
#
#   sudo bash bench/two_machines.sh                       # 8 envs, 2 sims, B unlimited
#   sudo B_CORES=0.5 bash bench/two_machines.sh           # machine B gets half a core
#   sudo ENVS=16 bash bench/two_machines.sh
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

ENVS=${ENVS:-8}
SIMS=${SIMS:-2}
STEPS=${STEPS:-24000}
B_CORES=${B_CORES:-}
PYTHON=${PYTHON:-python}
OUT=${OUT:-runs/two-machines-envs$ENVS-sims$SIMS-cores${B_CORES:-all}}
NS=swimm-b
A_IP=10.231.0.1
B_IP=10.231.0.2
CGROUP=/sys/fs/cgroup/cpu/swimm-b
NAMESPACE=swimm/two-machines
export MUJOCO_GL=${MUJOCO_GL:-egl}

if (( ENVS % SIMS )); then
    echo "ENVS ($ENVS) must be a multiple of SIMS ($SIMS)" >&2
    exit 2
fi
if [[ $EUID -ne 0 ]]; then
    echo "network namespaces and cgroups need root: run it with sudo" >&2
    exit 2
fi

pids=()
cleanup() {
    # SIGTERM (drain and exit), then SIGKILL for whatever is still there after 10 s
    for pid in "${pids[@]}"; do kill "$pid" 2>/dev/null || true; done
    for _ in $(seq 20); do
        alive=0
        for pid in "${pids[@]}"; do kill -0 "$pid" 2>/dev/null && alive=1; done
        ((alive)) || break
        sleep 0.5
    done
    for pid in "${pids[@]}"; do kill -9 "$pid" 2>/dev/null || true; done
    wait 2>/dev/null || true
    ip link del swimm-a 2>/dev/null || true
    ip netns del "$NS" 2>/dev/null || true
    [[ -d $CGROUP ]] && rmdir "$CGROUP" 2>/dev/null || true
}
trap cleanup EXIT

ip netns add "$NS"
ip link add swimm-a type veth peer name swimm-b0 netns "$NS"
ip addr add "$A_IP/24" dev swimm-a
ip link set swimm-a up
ip netns exec "$NS" ip addr add "$B_IP/24" dev swimm-b0
ip netns exec "$NS" ip link set swimm-b0 up
ip netns exec "$NS" ip link set lo up
mkdir -p "$CGROUP"
echo -1 > "$CGROUP/cpu.cfs_quota_us"  # unlimited unless B_CORES says otherwise
if [[ -n $B_CORES ]]; then
    awk -v cores="$B_CORES" -v period="$(cat "$CGROUP/cpu.cfs_period_us")" 'BEGIN { printf "%d\n", cores * period }' \
        > "$CGROUP/cpu.cfs_quota_us"
fi

mkdir -p "$OUT/logs"
# on_b COMMAND...: run a swimm command on machine B: into its cgroup first (`ip netns exec` mounts a /sys of the
# namespace's own, without the cgroup tree), then into its network namespace.
on_b() {
    exec bash -c 'set -e; echo $$ > "$0/cgroup.procs"; exec ip netns exec "$1" "${@:2}"' "$CGROUP" "$NS" "$@"
}
common=(--mode peer --connect "tcp/$A_IP:7447" --namespace "$NAMESPACE")

"$PYTHON" -m swimm router --listen "tcp/$A_IP:7447" > "$OUT/logs/router.log" 2>&1 &
pids+=($!)
sleep 2
share=$((ENVS / SIMS))
for ((i = 0; i < SIMS; i++)); do
    on_b "$PYTHON" -m swimm sim "${common[@]}" --listen "tcp/$B_IP:0" --train-envs "$share" \
        --first-train-env $((i * share)) --eval-envs 0 --ident "sim-$i" > "$OUT/logs/sim-$i.log" 2>&1 &
    pids+=($!)
done
on_b "$PYTHON" -m swimm encoder "${common[@]}" --listen "tcp/$B_IP:0" --threads 1 --ident enc-b \
    > "$OUT/logs/encoder.log" 2>&1 &
pids+=($!)

"$PYTHON" -m swimm learn "${common[@]}" --listen "tcp/$A_IP:0" --envs "$ENVS" --group-size "$share" \
    --steps "$STEPS" --resume learner_service/models/sac_cmvae.zip --no-eval-enabled --checkpoint-every 0 \
    --no-save-replay-buffer --run-dir "$OUT/learner" --no-progress-bar > "$OUT/logs/learner.log" 2>&1
cat "$OUT/learner/result.json"
echo
echo "machine B's cgroup (cpu.stat):"
cat "$CGROUP/cpu.stat"
