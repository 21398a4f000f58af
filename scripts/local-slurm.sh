#!/usr/bin/env bash
# A one-node SLURM cluster on this machine, for trying and testing the pipeline's SLURM path
# (configs/smoke-slurm.yaml, tests/test_slurm.py):
#
#   scripts/local-slurm.sh up       install slurm-wlm and munge if missing (as root, with apt-get), write a
#                                   munge key and a slurm.conf, start munged, slurmctld and slurmd, and wait
#                                   until the node is idle; a cluster already up is left as it is
#   scripts/local-slurm.sh down     cancel every job, stop the daemons it started (by their pid files)
#   scripts/local-slurm.sh status   the daemons, sinfo and squeue; exit 0 when up, 1 when not
#
# One node (this machine: `hostname -s`, its CPUs and memory from `slurmd -C`) in one default
# partition, `local`. A job asking for more CPUs or memory than that is refused by sbatch or never starts.
# Everything it writes (slurm.conf, state, spool, logs, pid files) goes under $LOCAL_SLURM_DIR
# (default /tmp/local-slurm); /etc/slurm/slurm.conf is made a link to that slurm.conf (so sbatch, squeue
# and sinfo find it without SLURM_CONF), and an existing /etc/slurm/slurm.conf that is not such a link
# is never touched: the script stops (this machine has a SLURM set-up of its own). The munge key is
# Debian's /etc/munge/munge.key (made when missing). Daemons run as root, started directly (no systemd).
set -euo pipefail

STATE=${LOCAL_SLURM_DIR:-/tmp/local-slurm}
CONF=$STATE/slurm.conf
ETC_CONF=/etc/slurm/slurm.conf
MUNGE_KEY=/etc/munge/munge.key
MUNGE_PID=/run/munge/munged.pid
PARTITION=local
NODE=$(hostname -s)
PACKAGES="slurm-wlm munge"
COMMANDS="munged slurmctld slurmd sinfo squeue sbatch scancel scontrol"

say() { echo "local-slurm: $*"; }
die() { echo "local-slurm: error: $*" >&2; exit 1; }

alive() {            # alive PIDFILE: the process of that pid file runs
    [ -s "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null
}

missing_commands() {
    local c out=""
    for c in $COMMANDS; do command -v "$c" >/dev/null 2>&1 || out="$out $c"; done
    echo "${out# }"
}

install_packages() {
    local missing
    missing=$(missing_commands)
    [ -z "$missing" ] && return 0
    if [ "$(id -u)" != 0 ]; then
        die "missing command(s): $missing (Debian packages: $PACKAGES); install them as root: apt-get install $PACKAGES"
    fi
    command -v apt-get >/dev/null 2>&1 \
        || die "missing command(s): $missing, and no apt-get to install them with; install SLURM (slurmctld, slurmd, client commands) and munge"
    say "installing $PACKAGES (missing: $missing)"
    # No systemd here: the packages' services are not started by the install (policy-rc.d refuses them).
    local policy=/usr/sbin/policy-rc.d made_policy=0
    if [ ! -e "$policy" ]; then
        printf '#!/bin/sh\nexit 101\n' > "$policy" && chmod 755 "$policy" && made_policy=1
    fi
    local rc=0
    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $PACKAGES; } \
        > "$STATE/apt.log" 2>&1 || rc=$?
    [ "$made_policy" = 1 ] && rm -f "$policy"
    [ "$rc" = 0 ] || { tail -n 20 "$STATE/apt.log" >&2; die "apt-get install $PACKAGES failed (exit $rc; log: $STATE/apt.log)"; }
    missing=$(missing_commands)
    [ -z "$missing" ] || die "installed $PACKAGES, but still missing: $missing"
}

start_munge() {
    if alive "$MUNGE_PID"; then
        return 0
    fi
    if [ ! -s "$MUNGE_KEY" ]; then
        say "writing a munge key: $MUNGE_KEY"
        mkdir -p /etc/munge
        dd if=/dev/urandom of="$MUNGE_KEY" bs=1024 count=1 status=none
    fi
    chown munge:munge "$MUNGE_KEY" && chmod 400 "$MUNGE_KEY"
    mkdir -p /run/munge /var/lib/munge /var/log/munge
    chown munge:munge /run/munge /var/lib/munge /var/log/munge
    chmod 755 /run/munge
    # --force: start even where munged finds a directory's permissions too open (e.g. a container's /)
    runuser -u munge -- munged --force --pid-file="$MUNGE_PID" \
        || die "munged did not start (log: /var/log/munge/munged.log)"
    touch "$STATE/run/munged.ours"
    local i
    for i in $(seq 50); do alive "$MUNGE_PID" && return 0; sleep 0.1; done
    die "munged did not start (log: /var/log/munge/munged.log)"
}

write_conf() {
    local cpus mem
    # the hardware's CPUs as slurmd sees them, not `nproc`: that is the calling process's affinity mask,
    # and a caller pinned to one core (a test process) wrote CPUs=1, so jobs ran one at a time
    cpus=$(slurmd -C 2>/dev/null | sed -n 's/.* CPUs=\([0-9]*\).*/\1/p' | head -n 1)
    [ -n "$cpus" ] || cpus=$(nproc --all)
    mem=$(slurmd -C 2>/dev/null | sed -n 's/.*RealMemory=\([0-9]*\).*/\1/p' | head -n 1)
    if [ -z "$mem" ]; then
        mem=$(awk '/^MemTotal:/ {print int($2 / 1024)}' /proc/meminfo)
    fi
    cat > "$CONF" <<EOF
# written by scripts/local-slurm.sh up: a one-node cluster on $NODE
ClusterName=local
SlurmctldHost=$NODE
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
MpiDefault=none
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerType=sched/backfill
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
ReturnToService=2
KillWait=5
MinJobAge=60
StateSaveLocation=$STATE/state
SlurmdSpoolDir=$STATE/spool
SlurmctldPidFile=$STATE/run/slurmctld.pid
SlurmdPidFile=$STATE/run/slurmd.pid
SlurmctldLogFile=$STATE/log/slurmctld.log
SlurmdLogFile=$STATE/log/slurmd.log
NodeName=$NODE CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=$PARTITION Nodes=$NODE Default=YES MaxTime=INFINITE State=UP
EOF
}

link_conf() {
    mkdir -p /etc/slurm
    if [ -L "$ETC_CONF" ] && [ "$(readlink "$ETC_CONF")" = "$CONF" ]; then
        return 0
    fi
    if [ -e "$ETC_CONF" ] || [ -L "$ETC_CONF" ]; then
        die "$ETC_CONF exists and is not local-slurm's: this machine has a SLURM set-up of its own, which local-slurm leaves alone (use that cluster, or move $ETC_CONF away first)"
    fi
    ln -s "$CONF" "$ETC_CONF"
}

node_state() {
    sinfo -h -n "$NODE" -o %T 2>/dev/null | head -n 1
}

wait_idle() {
    local i s=""
    for i in $(seq 60); do
        s=$(node_state)
        case "$s" in
            idle|mixed|allocated|completing) return 0 ;;
            down*|drain*)
                scontrol update NodeName="$NODE" State=RESUME >/dev/null 2>&1 || true ;;
        esac
        sleep 0.5
    done
    die "node $NODE is ${s:-not known to slurmctld} after 30 s (logs: $STATE/log/slurmctld.log, $STATE/log/slurmd.log)"
}

describe() {
    local line cpus mem
    line=$(scontrol show node "$NODE" 2>/dev/null | tr ' ' '\n')
    cpus=$(echo "$line" | sed -n 's/^CPUTot=//p')
    mem=$(echo "$line" | sed -n 's/^RealMemory=//p')
    say "up: node $NODE ($(node_state)), $cpus CPUs, $mem MB memory, partition '$PARTITION' (default); state in $STATE"
    say "a job asking for more than $cpus CPUs or $mem MB (sbatch --cpus-per-task / --mem; dask-jobqueue's cores / memory) is refused or never starts"
    say "stop it with: scripts/local-slurm.sh down"
}

is_up() {
    alive "$STATE/run/slurmctld.pid" && alive "$STATE/run/slurmd.pid" && [ -n "$(node_state)" ]
}

cmd_up() {
    if [ "$(id -u)" != 0 ]; then
        local missing
        missing=$(missing_commands)
        [ -z "$missing" ] || die "missing command(s): $missing (Debian packages: $PACKAGES); as root: apt-get install $PACKAGES"
        die "must run as root: slurmd starts jobs as their users and munged needs its key in /etc/munge"
    fi
    mkdir -p "$STATE"
    install_packages
    if is_up; then
        say "already running"
        describe
        return 0
    fi
    # a half-started cluster (one daemon left): stop it and start afresh
    stop_daemons
    mkdir -p "$STATE/state" "$STATE/spool" "$STATE/log" "$STATE/run"
    start_munge
    write_conf
    link_conf
    slurmctld -c -f "$CONF" || die "slurmctld did not start (log: $STATE/log/slurmctld.log)"
    # slurmd's "mpi/pmix_v4" error at start is harmless (no PMIx here; MpiDefault=none)
    slurmd -f "$CONF" -N "$NODE" || die "slurmd did not start (log: $STATE/log/slurmd.log)"
    local i
    for i in $(seq 50); do
        alive "$STATE/run/slurmctld.pid" && alive "$STATE/run/slurmd.pid" && break
        sleep 0.2
    done
    alive "$STATE/run/slurmctld.pid" || die "slurmctld exited (log: $STATE/log/slurmctld.log)"
    alive "$STATE/run/slurmd.pid" || die "slurmd exited (log: $STATE/log/slurmd.log)"
    wait_idle
    describe
}

stop_pid() {         # stop_pid NAME PIDFILE: TERM, then KILL after 10 s
    local name=$1 file=$2 pid i
    alive "$file" || { rm -f "$file"; return 0; }
    pid=$(cat "$file")
    kill "$pid" 2>/dev/null || true
    for i in $(seq 100); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
    if kill -0 "$pid" 2>/dev/null; then
        kill -9 "$pid" 2>/dev/null || true
        say "$name (pid $pid) did not stop in 10 s: killed"
    fi
    rm -f "$file"
    say "stopped $name (pid $pid)"
}

stop_daemons() {
    stop_pid slurmd "$STATE/run/slurmd.pid"
    stop_pid slurmctld "$STATE/run/slurmctld.pid"
}

cmd_down() {
    if alive "$STATE/run/slurmctld.pid"; then
        local jobs i
        jobs=$(squeue -h -o %i 2>/dev/null || true)
        if [ -n "$jobs" ]; then
            say "cancelling job(s): $(echo $jobs)"
            scancel $jobs 2>/dev/null || true
            for i in $(seq 60); do
                [ -z "$(squeue -h -o %i 2>/dev/null)" ] && break
                sleep 0.5
            done
        fi
    fi
    stop_daemons
    if [ -f "$STATE/run/munged.ours" ]; then
        stop_pid munged "$MUNGE_PID"
        rm -f "$STATE/run/munged.ours"
    fi
    if [ -L "$ETC_CONF" ] && [ "$(readlink "$ETC_CONF")" = "$CONF" ]; then
        rm -f "$ETC_CONF"
    fi
    local left
    left=$(pgrep -x slurmstepd || true)
    [ -z "$left" ] || say "warning: slurmstepd process(es) still running: $(echo $left) (jobs that did not end)"
    say "down (logs kept in $STATE/log)"
}

cmd_status() {
    local rc=0
    for d in slurmctld slurmd; do
        if alive "$STATE/run/$d.pid"; then say "$d: running (pid $(cat "$STATE/run/$d.pid"))"
        else say "$d: not running"; rc=1; fi
    done
    if alive "$MUNGE_PID"; then say "munged: running (pid $(cat "$MUNGE_PID"))"; else say "munged: not running"; rc=1; fi
    if [ "$rc" = 0 ]; then
        sinfo -N -o "%N %T %c %m %P" || rc=1
        squeue || rc=1
    fi
    return "$rc"
}

case "${1:-}" in
    up) cmd_up ;;
    down) cmd_down ;;
    status) cmd_status ;;
    *) echo "usage: $0 up|down|status   (a one-node SLURM cluster on this machine; state in $STATE)" >&2; exit 2 ;;
esac
