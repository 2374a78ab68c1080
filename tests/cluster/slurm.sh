#!/usr/bin/env bash
# The ci preset end to end on a real SLURM cluster, through Snakemake's SLURM executor plugin and the
# repository's profile (profiles/slurm), against a local run of the same preset.
#
#     bash tests/cluster/slurm.sh
#
# Opt-in: pytest does not collect tests/cluster (its conftest.py), and CI does not run it. It needs root on a
# Debian or Ubuntu machine (it installs slurm-wlm and munge with apt-get if slurmctld or munged is missing) and
# a Python with the workflow and the plugin: PYTHON, default .venv/bin/python, else python3
# (pip install -e '.[workflow,slurm]'). It
#
#   1. starts a one-node cluster on this machine: munged, slurmctld and slurmd, all under a temporary folder
#      (their own key, socket, ports, state and logs), but for /etc/slurm/slurm.conf, where the jobs' srun
#      finds it (written only where there is none, removed at the end), 2 CPUs, memory limits
#      enforced (a job over its mem_mb is killed), job completions logged to a file (jobcomp/filetxt: there
#      is no accounting database, so the plugin asks squeue for job states, and the log proves the jobs);
#   2. runs `snakemake --config dataset=ci` in one copy of the repository on the local cores, and with
#      `--profile profiles/slurm` in another, each job through sbatch;
#   3. checks that every job of the run was submitted with sbatch and completed in SLURM (the plugin's
#      submissions against the run's job list, each SLURM job in the completion log, COMPLETED, exit code 0),
#      and that no job ran locally;
#   4. checks that every product is identical to the local run's (tests/cluster/compare_runs.py);
#   5. stops the daemons and removes the folder, whatever happened (a trap). DICE_SLURM_KEEP=1 keeps the folder.
#
# Each SLURM job starts Snakemake twice on the node (the batch script, then srun), each parsing the workflow,
# so the SLURM run of the 68 ci jobs takes several times the local run's minute on an idle machine, and far
# longer on busy cores (2026-12-02, load average 20-30 on 2 cores: about 2 minutes a job, 2 at a time).
set -euo pipefail

REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
if [[ -z "${PYTHON:-}" ]]; then
    if [[ -x "$REPO/.venv/bin/python" ]]; then PYTHON="$REPO/.venv/bin/python"; else PYTHON=python3; fi
fi
PYTHON=$(command -v "$PYTHON")
START=$(date +%s)
say() { echo "[slurm.sh $(( $(date +%s) - START ))s] $*"; }
fail() { say "FAIL: $*"; exit 1; }

[[ $(id -u) -eq 0 ]] || fail "run as root (it installs and starts SLURM and munge)"
"$PYTHON" -c "import snakemake, snakemake_executor_plugin_slurm" 2>/dev/null \
    || fail "$PYTHON lacks snakemake or snakemake-executor-plugin-slurm: pip install -e '.[workflow,slurm]'"

if ! command -v slurmctld >/dev/null || ! command -v slurmd >/dev/null || ! command -v munged >/dev/null; then
    say "installing slurm-wlm and munge"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq slurm-wlm munge >/dev/null
fi

WORK=$(mktemp -d /tmp/dice-slurm.XXXXXX)
chmod 755 "$WORK"
cleanup() {
    local rc=$?
    set +e
    if [[ -n "${SLURM_CONF:-}" ]] && [[ $rc -ne 0 ]]; then
        say "slurmctld log (tail):"; tail -n 20 "$WORK/log/slurmctld.log" 2>/dev/null
        say "slurmd log (tail):"; tail -n 20 "$WORK/log/slurmd.log" 2>/dev/null
    fi
    if [[ -n "${LOCAL_PID:-}" ]]; then
        kill "$LOCAL_PID" 2>/dev/null
        wait "$LOCAL_PID" 2>/dev/null
    fi
    if [[ -n "${SLURM_CONF:-}" ]]; then
        scancel --quiet --user=root 2>/dev/null
    fi
    for pidfile in "$WORK/slurmd.pid" "$WORK/slurmctld.pid" "$WORK/munge/munged.pid"; do
        if [[ -s $pidfile ]]; then
            pid=$(cat "$pidfile")
            kill "$pid" 2>/dev/null
            for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.2; done
            kill -9 "$pid" 2>/dev/null
        fi
    done
    if [[ -e ${ETC_CONF:-} ]] && head -n 1 "$ETC_CONF" | grep -qF "$MARK"; then
        rm -f "$ETC_CONF"
    fi
    if [[ "${DICE_SLURM_KEEP:-0}" == 1 ]]; then
        say "kept $WORK"
    else
        rm -rf "$WORK"
    fi
    say "$([[ $rc -eq 0 ]] && echo PASSED || echo "FAILED (exit $rc)") in $(( $(date +%s) - START )) s"
}
trap cleanup EXIT

# ---------------------------------------------------------------------------------------------- the cluster
mkdir -p "$WORK/munge" "$WORK/state" "$WORK/spool" "$WORK/log"
chmod 700 "$WORK/munge"
dd if=/dev/urandom of="$WORK/munge/munge.key" bs=1024 count=1 status=none
chmod 400 "$WORK/munge/munge.key"
MUNGE_SOCKET="$WORK/munge.socket"
munged --force --socket="$MUNGE_SOCKET" --key-file="$WORK/munge/munge.key" --pid-file="$WORK/munge/munged.pid" \
    --log-file="$WORK/log/munged.log" --seed-file="$WORK/munge/munged.seed"
munge --socket="$MUNGE_SOCKET" --no-input | unmunge --socket="$MUNGE_SOCKET" >/dev/null || fail "munge does not work"

# two free TCP ports for slurmctld and slurmd, so that another cluster on this machine is no clash
read -r CTLD_PORT SLURMD_PORT < <("$PYTHON" -c "
import socket
sockets = [socket.socket() for _ in range(2)]
for s in sockets: s.bind(('127.0.0.1', 0))
print(*[s.getsockname()[1] for s in sockets])")
# The job's own Snakemake starts each step with srun, clearing SLURM_* variables, SLURM_CONF among them: the
# configuration must be where SLURM looks by default. One left there by an earlier run of this script is
# replaced; any other is a real cluster's, and this script stops.
ETC_CONF=/etc/slurm/slurm.conf
MARK="# written by the DICE pipeline's tests/cluster/slurm.sh, removed when it ends"
if [[ -e $ETC_CONF ]] && ! head -n 1 "$ETC_CONF" | grep -qF "$MARK"; then
    fail "$ETC_CONF exists: this machine has a SLURM configuration of its own; run this test elsewhere"
fi
HOST=$(hostname -s)
MEM_MB=$(awk '/MemTotal/ {print int($2 / 1024 / 2)}' /proc/meminfo)   # half the machine: enough for the ci jobs
mkdir -p /etc/slurm
cat > "$WORK/slurm.conf" <<EOF
$MARK
ClusterName=dicetest
SlurmctldHost=$HOST(127.0.0.1)
SlurmctldPort=$CTLD_PORT
SlurmdPort=$SLURMD_PORT
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$MUNGE_SOCKET
StateSaveLocation=$WORK/state
SlurmdSpoolDir=$WORK/spool
SlurmctldPidFile=$WORK/slurmctld.pid
SlurmdPidFile=$WORK/slurmd.pid
SlurmctldLogFile=$WORK/log/slurmctld.log
SlurmdLogFile=$WORK/log/slurmd.log
# a container without systemd or a writable cgroup tree: processes tracked by their parentage, no task binding
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
MpiDefault=none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU_Memory
SchedulerType=sched/backfill
ReturnToService=2
# finished jobs stay visible to squeue for an hour: the plugin's status queries use squeue (no database)
MinJobAge=3600
# no accounting database; each job's end is written to a file, which proves it ran
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/filetxt
JobCompLoc=$WORK/jobcomp.log
# memory sampled every 2 s, a job over its request killed: the rules' mem_mb must suffice
JobAcctGatherType=jobacct_gather/linux
JobAcctGatherFrequency=task=2
JobAcctGatherParams=OverMemoryKill
NodeName=$HOST NodeAddr=127.0.0.1 CPUs=2 RealMemory=$MEM_MB State=UNKNOWN
PartitionName=dice Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
EOF
cp "$WORK/slurm.conf" "$ETC_CONF"
export SLURM_CONF=$ETC_CONF
slurmctld -f "$SLURM_CONF"
slurmd -f "$SLURM_CONF"
for _ in $(seq 60); do
    [[ $(sinfo --noheader --format=%T 2>/dev/null) == idle ]] && break
    sleep 1
done
[[ $(sinfo --noheader --format=%T) == idle ]] || fail "the node is not idle: $(sinfo --noheader)"
say "cluster up: node $HOST, 2 CPUs, ${MEM_MB} MB, slurmctld port $CTLD_PORT ($(sinfo --version))"

# The memory limits are enforced: a job that touches 400 MB with 50 MB asked for is killed.
canary=$(sbatch --parsable --mem=50 --cpus-per-task=1 --time=2 --job-name=dice-memory-canary \
    --output="$WORK/canary.out" --wrap "$PYTHON -c 'import time; a = bytes(range(256)) * (1600 * 1024); time.sleep(10); print(\"survived\")'")
for _ in $(seq 120); do grep -q "JobId=$canary " "$WORK/jobcomp.log" 2>/dev/null && break; sleep 1; done
grep -q "exceeded memory limit" "$WORK/canary.out" && ! grep -q survived "$WORK/canary.out" \
    || fail "SLURM does not enforce memory limits here: $(cat "$WORK/canary.out")"
say "memory limits enforced: job $canary, 400 MB touched with 50 MB asked for, killed"

# ----------------------------------------------------------------------------------- the two runs of ci
copy() {
    mkdir -p "$1"
    for item in Snakefile workflow config dice_core profiles; do cp -r "$REPO/$item" "$1/"; done
    find "$1" -name __pycache__ -prune -exec rm -rf {} +
}
copy "$WORK/local"
copy "$WORK/slurm"

# The local run goes alongside the SLURM run (the node's 2 CPUs are this machine's).
say "local run: snakemake --cores 2 --config dataset=ci, in the background"
t_local=$(date +%s)
(cd "$WORK/local" && PYTHONPATH="$WORK/local" exec "$PYTHON" -m snakemake --cores 2 --config dataset=ci \
    >"$WORK/local.log" 2>&1) &
LOCAL_PID=$!

# Cluster-specific settings on the command line, the profile as users get it: no accounts or database here,
# so no account and job states from squeue; the first status check after 5 s instead of 40; no retry, so
# that a job killed for its memory or time fails the test; the SLURM logs of successful jobs kept.
say "SLURM run: snakemake --profile profiles/slurm --config dataset=ci"
t0=$(date +%s)
(cd "$WORK/slurm" && PYTHONPATH="$WORK/slurm" "$PYTHON" -m snakemake --profile profiles/slurm --config dataset=ci \
    --slurm-no-account --slurm-status-command squeue --slurm-init-seconds-before-status-checks 5 \
    --slurm-keep-successful-logs --retries 0 >"$WORK/slurm.log" 2>&1) \
    || { tail -n 60 "$WORK/slurm.log"; fail "the SLURM run failed"; }
say "SLURM run done in $(( $(date +%s) - t0 )) s: $(grep -c 'has been submitted with SLURM jobid' "$WORK/slurm.log") jobs"
wait "$LOCAL_PID" || { tail -n 40 "$WORK/local.log"; fail "the local run failed"; }
LOCAL_PID=
say "local run done in $(( $(date +%s) - t_local )) s"

# ------------------------------------------------------------------------------------------------ checks
"$PYTHON" "$REPO/tests/cluster/compare_runs.py" jobs --local-log "$WORK/local.log" --slurm-log "$WORK/slurm.log" \
    --jobcomp "$WORK/jobcomp.log" || fail "not every job ran through sbatch"
"$PYTHON" "$REPO/tests/cluster/compare_runs.py" products "$WORK/local/results/sim-ci" "$WORK/slurm/results/sim-ci" \
    || fail "the SLURM run's products differ from the local run's"
