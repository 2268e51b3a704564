#!/usr/bin/env bash
# A single-node Slurm cluster on this machine, from Debian's packages, for trying and testing the
# Slurm profile (profiles/slurm) without a real cluster. Run as root:
#
#   bash scripts/slurm-cluster.sh start     # install what is missing, start munge, MariaDB, slurmdbd,
#                                           # slurmctld and slurmd; prints how long it took
#   bash scripts/slurm-cluster.sh status    # sinfo and the accounting's cluster list
#   bash scripts/slurm-cluster.sh stop      # stop the daemons it started and remove the configuration
#                                           # it wrote (state is kept; start writes it again)
#   bash scripts/slurm-cluster.sh purge     # stop, then delete its state, logs and configuration
#
# Accounting is real (slurmdbd on a local MariaDB), because the Snakemake Slurm executor asks `sacct`
# for job states; job ids and states can then be checked with `sacct`. The node offers this
# machine's CPUs and 90% of its memory in one partition, `main`, and no GPUs.
#
# It refuses to touch a machine that has any Slurm of its own: SLURM_CONF set to a file it did not
# write, a configless node's cached configuration, a Slurm configuration it did not write (in
# /etc/slurm or /etc/slurm-llnl), or a Slurm daemon running that it did not start. It writes
# /etc/slurm/slurm.conf and /etc/slurm/slurmdbd.conf only when they are absent or its own (a marker
# line); `stop` removes them again (only when they carry the marker): while a configuration names a
# controller that is not running, every Slurm command waits about 9 s for it, and Snakemake's Slurm
# executor plugin runs one (`scontrol show config`) each time Snakemake starts, on any workflow run;
# without a configuration Slurm's tools fail at once. A MariaDB or munged already running (for example started by their Debian packages) is
# used as it is and left running. `purge` deletes only a state folder this script made (a marker file).
# Environment: TANGO_SLURM_STATE (default /var/lib/tango-slurm): databases, spool, logs, pid files;
# TANGO_SLURM_INSTALL=0 to fail instead of installing missing packages with apt-get.
set -euo pipefail
# the daemons and admin tools live in sbin, which a non-login root shell may not have on PATH
export PATH="/usr/sbin:/sbin:$PATH"

state=${TANGO_SLURM_STATE:-/var/lib/tango-slurm}
conf_dir=${TANGO_SLURM_CONF_DIR:-/etc/slurm} # (another folder: the script's own tests)
marker="# written by tango-stylize scripts/slurm-cluster.sh"
cluster=tango
packages=(slurm-wlm slurmdbd munge mariadb-server)

die() {
    echo "slurm-cluster: $*" >&2
    exit 1
}

need_root() {
    [ "$(id -u)" = 0 ] || die "must run as root (it starts system daemons and writes /etc/slurm)"
}

install_missing() {
    local missing=()
    command -v slurmctld >/dev/null || missing+=(slurm-wlm)
    command -v slurmdbd >/dev/null || missing+=(slurmdbd)
    command -v munged >/dev/null || missing+=(munge)
    command -v mariadbd >/dev/null || [ -x /usr/sbin/mariadbd ] || missing+=(mariadb-server)
    [ ${#missing[@]} -eq 0 ] && return
    [ "${TANGO_SLURM_INSTALL:-1}" = 1 ] || die "missing packages: ${missing[*]} (apt-get install ${packages[*]})"
    echo "slurm-cluster: installing ${missing[*]}"
    # the packages' own service start-up is not wanted (this script starts what it needs): a
    # policy-rc.d that says no, put back as it was afterwards, whatever happens
    local policy=/usr/sbin/policy-rc.d backup=""
    if [ -e "$policy" ]; then
        backup=$(mktemp)
        cp -p "$policy" "$backup"
    fi
    # shellcheck disable=SC2064
    trap "if [ -n '$backup' ]; then mv -f '$backup' '$policy'; else rm -f '$policy'; fi" EXIT
    printf '#!/bin/sh\nexit 101\n' > "$policy" && chmod +x "$policy"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
    if [ -n "$backup" ]; then mv -f "$backup" "$policy"; else rm -f "$policy"; fi
    trap - EXIT
}

state_marker="$state/.made-by-tango-slurm-cluster"

ours_running() { # name: a live process of that name whose pid this script recorded when it started it
    local list="$state/run/launched" name pidfile pid
    [ -s "$list" ] || return 1
    while read -r name pidfile; do
        [ "$name" = "$1" ] || continue
        pid=$(cat "$pidfile" 2>/dev/null || true)
        [ -n "$pid" ] && [ "$(cat "/proc/$pid/comm" 2>/dev/null)" = "$1" ] && return 0
    done < "$list"
    return 1
}

is_ours() { # a configuration this script wrote: the marker is its first line (a comment elsewhere does not count)
    [ -f "$1" ] && [ "$(head -n 1 "$1" 2>/dev/null)" = "$marker" ]
}

refuse_foreign_slurm() { # stop before anything is installed, written or started
    local f d name
    if [ -n "${SLURM_CONF:-}" ] && ! is_ours "$SLURM_CONF"; then
        die "SLURM_CONF is set ($SLURM_CONF) and names a configuration this script did not write: this machine has a Slurm of its own (stop here)"
    fi
    for d in /run/slurm/conf /var/spool/slurmd/conf-cache; do
        [ ! -e "$d" ] || die "$d exists: this is a configless Slurm node of a real cluster (stop here)"
    done
    # Debian's, older Debian's and a source-built Slurm's default folders
    for f in /etc/slurm/slurm.conf /etc/slurm/slurmdbd.conf /etc/slurm-llnl/slurm.conf /etc/slurm-llnl/slurmdbd.conf \
        /usr/local/etc/slurm.conf /usr/local/etc/slurmdbd.conf; do
        [ ! -e "$f" ] || is_ours "$f" || die "$f exists and was not written by this script: is this machine part of a real cluster? (stop here)"
    done
    for name in slurmctld slurmd slurmdbd slurmrestd sackd; do  # (not slurmstepd: a job step of ours outlives slurmd)
        if pgrep -x "$name" >/dev/null 2>&1 && ! ours_running "$name"; then
            die "$name is running and was not started by this script: this machine has a Slurm of its own (stop here)"
        fi
    done
}

ours_or_absent() {
    [ ! -e "$1" ] || is_ours "$1" || die "$1 exists and was not written by this script: is this machine part of a real cluster? (stop here)"
}

write_configs() {
    ours_or_absent "$conf_dir/slurm.conf"
    ours_or_absent "$conf_dir/slurmdbd.conf"
    # (a folder with this script's layout but no marker: made by its earlier version, before markers)
    [ ! -e "$state" ] || [ -e "$state_marker" ] || [ -z "$(ls -A "$state")" ] || [ -d "$state/spool/ctld" ] \
        || die "$state holds files this script did not make: set TANGO_SLURM_STATE to a new folder"
    mkdir -p "$conf_dir" "$state"/{spool/ctld,spool/d,log,run,mysql}
    touch "$state_marker"
    local host cpus mem
    host=$(hostname -s)
    # the machine's CPUs, not a caller's OMP_NUM_THREADS (which nproc honours: a test worker sets it)
    cpus=$(env -u OMP_NUM_THREADS -u OMP_THREAD_LIMIT nproc)
    mem=$(awk '/MemTotal/ {printf "%d", $2 / 1024 * 0.9}' /proc/meminfo)
    cat > "$conf_dir/slurm.conf" <<EOF
$marker
ClusterName=$cluster
SlurmctldHost=$host(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$state/spool/ctld
SlurmdSpoolDir=$state/spool/d
SlurmctldPidFile=$state/run/slurmctld.pid
SlurmdPidFile=$state/run/slurmd.pid
SlurmctldLogFile=$state/log/slurmctld.log
SlurmdLogFile=$state/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
SchedulerType=sched/backfill
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=localhost
JobAcctGatherType=jobacct_gather/linux
JobAcctGatherFrequency=10
JobCompType=jobcomp/filetxt
JobCompLoc=$state/log/jobcomp.log
# finished jobs stay visible to squeue for 10 minutes; sacct keeps them for good
MinJobAge=600
# a job past its time limit is signalled at once and killed 5 s later (the defaults wait longer)
OverTimeLimit=0
KillWait=5
ReturnToService=2
NodeName=$host NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=main Nodes=$host Default=YES MaxTime=INFINITE State=UP
EOF
    cat > "$conf_dir/slurmdbd.conf" <<EOF
$marker
AuthType=auth/munge
DbdHost=localhost
SlurmUser=root
PidFile=$state/run/slurmdbd.pid
LogFile=$state/log/slurmdbd.log
StorageType=accounting_storage/mysql
StorageHost=localhost
StoragePort=3306
StorageUser=root
StorageLoc=slurm_acct_db
EOF
    chmod 600 "$conf_dir/slurmdbd.conf"
}

wait_for() { # seconds, description, command...
    local n=$(($1 * 10)) what=$2
    shift 2
    for _ in $(seq "$n"); do
        "$@" >/dev/null 2>&1 && return 0
        sleep 0.1
    done
    die "$what did not come up (logs in $state/log)"
}

launched() { # name, pid file: a daemon this script started (stop stops only these)
    echo "$1 $2" >> "$state/run/launched"
}

start() {
    need_root
    local t0=$SECONDS
    refuse_foreign_slurm
    install_missing
    write_configs
    # munge: one key for the one node
    [ -s /etc/munge/munge.key ] || mungekey --create --force >/dev/null 2>&1 || mungekey -c
    chown munge:munge /etc/munge/munge.key && chmod 400 /etc/munge/munge.key
    mkdir -p /run/munge && chown munge:munge /run/munge
    if ! munge -n >/dev/null 2>&1; then
        runuser -u munge -- /usr/sbin/munged
        launched munged /run/munge/munged.pid
    fi
    wait_for 10 munged munge -n
    # MariaDB with its data under the state folder; root connects over the local socket (a
    # server already answering there is used as it is, and left running by stop)
    if [ ! -d "$state/mysql/mysql" ]; then
        mariadb-install-db --user=mysql --datadir="$state/mysql" --auth-root-authentication-method=socket >/dev/null
    fi
    mkdir -p /run/mysqld && chown mysql:mysql /run/mysqld
    if ! mariadb-admin ping >/dev/null 2>&1; then
        /usr/sbin/mariadbd --user=mysql --datadir="$state/mysql" --socket=/run/mysqld/mysqld.sock \
            --pid-file=/run/mysqld/mariadb.pid --port=3306 --bind-address=127.0.0.1 \
            --innodb-buffer-pool-size=64M --log-error="$state/mysql/mariadb.log" >/dev/null 2>&1 &
        launched mariadbd /run/mysqld/mariadb.pid
    fi
    wait_for 30 MariaDB mariadb-admin ping
    if ! ours_running slurmdbd; then
        /usr/sbin/slurmdbd
        launched slurmdbd "$state/run/slurmdbd.pid"
    fi
    wait_for 30 slurmdbd sacctmgr -n show cluster
    # the cluster and an account for root, so that jobs are accounted and `sacct` finds them
    sacctmgr -i -Q add cluster "$cluster" >/dev/null 2>&1 || true
    sacctmgr -i -Q add account tango Cluster="$cluster" Description=tango Organization=tango >/dev/null 2>&1 || true
    sacctmgr -i -Q add user root Account=tango Cluster="$cluster" >/dev/null 2>&1 || true
    if ! ours_running slurmctld; then
        /usr/sbin/slurmctld
        launched slurmctld "$state/run/slurmctld.pid"
    fi
    wait_for 30 slurmctld scontrol ping
    if ! ours_running slurmd; then
        /usr/sbin/slurmd
        launched slurmd "$state/run/slurmd.pid"
    fi
    wait_for 30 "the node" sh -c "sinfo -h -o %t | grep -Eq '^(idle|mix|alloc)'"
    echo "slurm-cluster: up in $((SECONDS - t0)) s: $(sinfo -h -o '%P %D nodes %c CPUs %m MB %t')"
}

stop_one() { # name, pid file: only a live process of that name
    local pid
    pid=$(cat "$2" 2>/dev/null || true)
    [ -n "$pid" ] && [ "$(cat "/proc/$pid/comm" 2>/dev/null)" = "$1" ] || return 0
    kill "$pid" 2>/dev/null || true
    for _ in $(seq 100); do kill -0 "$pid" 2>/dev/null || return 0; sleep 0.1; done
    kill -9 "$pid" 2>/dev/null || true
}

remove_own_configs() { # only files that carry the marker: a configuration of another Slurm stays
    local f
    for f in "$conf_dir/slurm.conf" "$conf_dir/slurmdbd.conf"; do
        if is_ours "$f"; then rm -f "$f"; fi
    done
}

stop() {
    need_root
    local list="$state/run/launched"
    if [ ! -s "$list" ]; then
        remove_own_configs
        echo "slurm-cluster: nothing to stop (no daemon started by this script is recorded in $list)"
        return 0
    fi
    # the reverse of the start order: slurmd, slurmctld, slurmdbd, MariaDB, munged
    tac "$list" | while read -r name pidfile; do stop_one "$name" "$pidfile"; done
    rm -f "$list"
    remove_own_configs
    echo "slurm-cluster: stopped"
}

case "${1:-}" in
    start) start ;;
    stop) stop ;;
    status)
        sinfo
        sacctmgr -n show cluster format=cluster,controlhost
        ;;
    purge)
        need_root
        [ ! -e "$state" ] || [ -e "$state_marker" ] || [ -d "$state/spool/ctld" ] \
            || die "$state was not made by this script (no $state_marker): not deleting it, nor anything else"
        stop
        rm -rf "$state"
        echo "slurm-cluster: state removed"
        ;;
    *) die "usage: $0 start|status|stop|purge" ;;
esac
