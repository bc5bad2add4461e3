#!/usr/bin/env bash
# A job larger than any one worker's memory, completed across several workers, each in a
# memory-limited cgroup (docs/scaling.md, "A worker's memory").
#
#   bash docs/scaling/memory-limited.sh [VLF] [WORKERS] [LIMIT_MB] [BUDGET]
#
# 1. `vlf propagate` runs the job in one process, unlimited: the reference field and its peak
#    memory.
# 2. One worker in a cgroup of LIMIT_MB without a subfield budget: it must build every
#    subfield, does not fit, and is killed (the kernel's OOM killer) — the job cannot finish
#    on it.
# 3. WORKERS workers, each in its own cgroup of LIMIT_MB with `--subfield-memory BUDGET`, finish
#    the job (the coordinator holds BUDGET of subfields too); its stored field must be the
#    reference's, byte for byte.
#
# Needs write access to the cgroup file system (v1 `memory` controller or v2 with `memory` in
# `cgroup.subtree_control`), as root in a VM or container that allows it. Prints each
# process's peak resident memory (GNU time) and exits non-zero if a check fails.
set -euo pipefail

VLF=${1:-target/release/vlf}
WORKERS=${2:-3}
LIMIT_MB=${3:-200}
BUDGET=${4:-40MB}
SCENE=${SCENE:-scenes/cornell.obj}
FLAGS=(--directions 8193 --resolution 128 --iterations 4 --encoding f32)
WORK=$(mktemp -d /tmp/vlf-memory-XXXXXX)
# The coordinators' process ids and the cgroups made, for the clean-up (set in this shell, not
# in command substitutions' subshells).
SERVERS=""
CGROUPS=""

cleanup() {
    for p in $SERVERS; do kill "$p" 2>/dev/null || true; done
    for g in $CGROUPS; do
        while read -r p; do kill -KILL "$p" 2>/dev/null || true; done < "$g/cgroup.procs"
    done
    wait 2>/dev/null || true
    # A killed process leaves its cgroup a moment later.
    for g in $CGROUPS; do
        for _ in $(seq 50); do rmdir "$g" 2>/dev/null && break; sleep 0.1; done
    done
}
trap cleanup EXIT

# A cgroup limited to LIMIT_MB, into $group.
limited_cgroup() {
    local name=vlf-$1-$$ dir
    if [ -d /sys/fs/cgroup/memory ]; then
        dir=/sys/fs/cgroup/memory/$name
        mkdir "$dir"
        echo $((LIMIT_MB << 20)) > "$dir/memory.limit_in_bytes"
    else
        dir=/sys/fs/cgroup/$name
        mkdir "$dir"
        echo $((LIMIT_MB << 20)) > "$dir/memory.max"
        echo 0 > "$dir/memory.swap.max" 2>/dev/null || true
    fi
    CGROUPS="$CGROUPS $dir"
    group=$dir
}

# Runs "$@" in cgroup $1 (the rest: the command), under GNU time into $WORK/$2.time.
in_cgroup() {
    local dir=$1 name=$2
    shift 2
    sh -c 'echo $$ > "$0/cgroup.procs" && exec "$@"' "$dir" \
        /usr/bin/time -f "%M" -o "$WORK/$name.time" "$@" > "$WORK/$name.log" 2>&1
}

field_digest() {
    find "$1" -path '*/field/*' -name '*.blob' ! -name summary.blob | sort | xargs cat | sha256sum | cut -d' ' -f1
}

echo "== reference: vlf propagate, one process, no limit"
/usr/bin/time -f "%M" -o "$WORK/reference.time" \
    "$VLF" propagate "$SCENE" --store "$WORK/reference" "${FLAGS[@]}" > "$WORK/reference.log" 2>&1
grep -E "field memory|time split" "$WORK/reference.log"
echo "   peak resident $(( $(cat "$WORK/reference.time") / 1024 )) MB"
want=$(field_digest "$WORK/reference")

# A coordinator on a free port over store $WORK/$1 (the rest: its flags); its URL into $url,
# its process id into $server.
serve() {
    local store=$1
    shift
    "$VLF" serve --store "$WORK/$store" --listen 127.0.0.1:0 "$@" > "$WORK/$store-serve.log" 2>&1 &
    server=$!
    SERVERS="$SERVERS $server"
    url=""
    for _ in $(seq 100); do
        url=$(sed -n 's/^listening on //p' "$WORK/$store-serve.log")
        [ -n "$url" ] && return
        sleep 0.1
    done
    echo "FAIL: the coordinator did not start"; cat "$WORK/$store-serve.log"; exit 1
}

# The first line of `vlf submit`'s output (the job id).
submit() {
    "$VLF" submit "$SCENE" --server "$url" "${FLAGS[@]}" > "$WORK/submit.log"
    head -1 "$WORK/submit.log"
}

echo "== one worker limited to $LIMIT_MB MB, all subfields held"
serve whole
limited_cgroup whole
in_cgroup "$group" whole "$VLF" worker --server "$url" --threads 2 --name whole &
worker=$!
id=$(submit)
# Until the worker dies or the job ends (a worker does not exit when a job ends).
"$VLF" watch "$id" --server "$url" > "$WORK/whole-watch.log" 2>&1 &
watch=$!
while kill -0 "$worker" 2>/dev/null && kill -0 "$watch" 2>/dev/null; do sleep 1; done
if kill -0 "$worker" 2>/dev/null; then
    echo "FAIL: the unbudgeted worker ran within $LIMIT_MB MB: raise the job's size or lower the limit"
    exit 1
fi
kill "$watch" 2>/dev/null || true
wait "$watch" 2>/dev/null || true
wait "$worker" || true
echo "   the worker was killed, as expected: $(head -1 "$WORK/whole.time")"
echo "   the job: $("$VLF" status "$id" --server "$url" | head -1)"

echo "== $WORKERS workers limited to $LIMIT_MB MB each, --subfield-memory $BUDGET"
serve budget --subfield-memory "$BUDGET"
workers=""
for w in $(seq "$WORKERS"); do
    limited_cgroup "w$w"
    in_cgroup "$group" "w$w" "$VLF" worker --server "$url" --threads 1 --name "w$w" --subfield-memory "$BUDGET" &
    workers="$workers $!"
done
id=$(submit)
start=$SECONDS
"$VLF" watch "$id" --server "$url" > "$WORK/watch.log" 2>&1 || { cat "$WORK/watch.log"; exit 1; }
echo "   finished in $((SECONDS - start)) s"
# SIGTERM to the workers themselves (not to GNU time, which then reports their peak).
for w in $(seq "$WORKERS"); do pkill -TERM -f "^$VLF worker .*--name w$w( |$)" || true; done
for p in $workers; do wait "$p" || true; done
for w in $(seq "$WORKERS"); do
    echo "   worker $w peak resident $(( $(tail -1 "$WORK/w$w.time") / 1024 )) MB"
done
echo "   coordinator peak resident so far $(( $(awk '/VmHWM/ {print $2}' "/proc/$server/status") / 1024 )) MB"
got=$(field_digest "$WORK/budget")
if [ "$got" != "$want" ]; then
    echo "FAIL: the stored field differs from the reference"
    exit 1
fi
echo "   the stored field is the reference's, byte for byte"
