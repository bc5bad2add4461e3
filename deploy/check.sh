#!/usr/bin/env bash
# The deployment check: starts the service (a coordinator, its object store and two workers),
# submits the Cornell box, scales the workers up while the job runs, kills one, scales them
# down, and checks that the field the service made has the bits of a local `vlf propagate` (the
# digests `vlf status` and `vlf propagate` print: SHA-256 of the field's radiance).
#
#   bash deploy/check.sh RUNTIME [VLF]
#
# RUNTIME is where the service runs:
#   local    `vlf serve` and `vlf worker` processes on this machine (a directory store)
#   compose  deploy/compose.yaml on this Docker host (MinIO, the image built from the tree)
#   kind     deploy/k8s on a kind cluster `vlf-check` (made if missing, deleted if made here)
#   k3d      the same on a k3d cluster
# VLF is the client binary (default: target/release/vlf, built if missing). The job's shape is
# L directions, N rays a side, K iterations (environment; default 2049, 64, 11: a minute or so
# on 2 cores, long enough to scale while it runs). Exits 0 when the bits are the same, 1 when
# they differ, 2 when the check could not run. Needs docker for compose (Compose v2, or v1's
# docker-compose), and kind or k3d with kubectl for those.
#
# The service's image is built from the tree (deploy/Dockerfile) unless VLF_CHECK_IMAGE names
# one to check instead (the published image, or one built elsewhere). VLF_CHECK_COMPOSE_FILES
# (colon-separated) adds compose files over deploy/compose.yaml, e.g. one that takes the store's
# image from a registry mirror.
set -euo pipefail
RUNTIME=${1:-}
ROOT=$(cd "$(dirname "$0")/.." && pwd)
VLF=${2:-$ROOT/target/release/vlf}
L=${L:-2049}
N=${N:-64}
K=${K:-11}
SCENE=$ROOT/scenes/cornell.obj
SHAPE=(--directions "$L" --resolution "$N" --iterations "$K")
NS=vlf-check
CLUSTER=vlf-check
PORT=${VLF_CHECK_PORT:-7474}
WORK=$(mktemp -d "${TMPDIR:-/tmp}/vlf-check-XXXXXX")
export VLF_TOKEN=${VLF_TOKEN:-$(head -c 16 /dev/urandom | od -An -tx1 | tr -d ' \n')}
export AWS_ACCESS_KEY_ID=${AWS_ACCESS_KEY_ID:-vlfcheck}
export AWS_SECRET_ACCESS_KEY=${AWS_SECRET_ACCESS_KEY:-$(head -c 16 /dev/urandom | od -An -tx1 | tr -d ' \n')}

say() { printf '== %s\n' "$*"; }
fail() { printf 'check: %s\n' "$*" >&2; exit 2; }
need() { command -v "$1" >/dev/null 2>&1 || fail "$RUNTIME needs $1"; }

case $RUNTIME in
  local) ;;
  compose) need docker ;;
  kind | k3d) need docker; need kubectl; need "$RUNTIME" ;;
  *) sed -n '2,23p' "$0"; exit 2 ;;
esac
if [ ! -x "$VLF" ]; then
  say "building $VLF"
  (cd "$ROOT" && cargo build --release -p vlf --bin vlf)
fi

# --- the runtimes: up (two workers; sets URL), scale COUNT, kill_one, down -----------------

WORKER_PIDS=()
local_up() {
  "$VLF" serve --store "$WORK/store" --listen "127.0.0.1:$PORT" >"$WORK/serve.log" 2>&1 &
  SERVE_PID=$!
  URL=http://127.0.0.1:$PORT
  "$VLF" health --server "$URL" --wait 30 >/dev/null || fail "the coordinator did not start: $(cat "$WORK/serve.log")"
  local_scale 2
}
local_scale() {
  while [ ${#WORKER_PIDS[@]} -lt "$1" ]; do
    "$VLF" worker --server "$URL" --threads 1 >>"$WORK/workers.log" 2>&1 &
    WORKER_PIDS+=($!)
  done
  while [ ${#WORKER_PIDS[@]} -gt "$1" ]; do
    # As a runtime scales down: SIGTERM, and the worker sends its reports before it exits.
    local last=${WORKER_PIDS[-1]}
    kill -TERM "$last"
    wait "$last" || fail "a worker stopped with SIGTERM exited with $?"
    unset 'WORKER_PIDS[-1]'
  done
}
local_kill_one() {
  kill -KILL "${WORKER_PIDS[0]}"
  wait "${WORKER_PIDS[0]}" 2>/dev/null || true
  WORKER_PIDS=("${WORKER_PIDS[@]:1}")
}
local_down() {
  for p in "${WORKER_PIDS[@]}"; do kill -KILL "$p" 2>/dev/null || true; done
  [ -n "${SERVE_PID:-}" ] && kill -TERM "$SERVE_PID" 2>/dev/null || true
  wait 2>/dev/null || true
}

# Compose v2 (`docker compose`) where the Docker CLI has it, v1 (`docker-compose`) otherwise,
# on the service's file and the user's (VLF_CHECK_COMPOSE_FILES).
compose_files() {
  local f files=(-f "$ROOT/deploy/compose.yaml")
  local IFS=:
  for f in ${VLF_CHECK_COMPOSE_FILES:-}; do files+=(-f "$f"); done
  printf '%s\n' "${files[@]}"
}
if [ "$RUNTIME" = compose ]; then
  if docker compose version >/dev/null 2>&1; then COMPOSE=(docker compose); else need docker-compose; COMPOSE=(docker-compose); fi
  mapfile -t FILES < <(compose_files)
  COMPOSE+=("${FILES[@]}" -p vlf-check)
fi
compose_up() {
  [ "$PORT" = 7464 ] || say "compose publishes the coordinator on 7464"
  PORT=7464
  URL=http://127.0.0.1:$PORT
  if [ -n "${VLF_CHECK_IMAGE:-}" ]; then
    docker tag "$VLF_CHECK_IMAGE" vlf:latest
    "${COMPOSE[@]}" up --no-build -d coordinator
  else
    "${COMPOSE[@]}" up --build -d coordinator
  fi
  "$VLF" health --server "$URL" --wait 120 >/dev/null || fail "the coordinator did not start: $("${COMPOSE[@]}" logs --tail 20 2>&1)"
  compose_scale 2
}
compose_scale() { "${COMPOSE[@]}" up -d --no-recreate --scale "worker=$1" worker; }
compose_kill_one() { docker kill "$("${COMPOSE[@]}" ps -q worker | head -n 1)" >/dev/null; }
compose_down() { "${COMPOSE[@]}" down -v >/dev/null 2>&1 || true; }

MADE_CLUSTER=""
k8s_up() {
  if [ "$RUNTIME" = kind ]; then
    kind get clusters 2>/dev/null | grep -qx "$CLUSTER" || { kind create cluster --name "$CLUSTER"; MADE_CLUSTER=1; }
    kubectl config use-context "kind-$CLUSTER" >/dev/null
  else
    k3d cluster list "$CLUSTER" >/dev/null 2>&1 || { k3d cluster create "$CLUSTER"; MADE_CLUSTER=1; }
    kubectl config use-context "k3d-$CLUSTER" >/dev/null
  fi
  if [ -n "${VLF_CHECK_IMAGE:-}" ]; then
    docker tag "$VLF_CHECK_IMAGE" vlf:check
  else
    docker build -f "$ROOT/deploy/Dockerfile" -t vlf:check "$ROOT"
  fi
  if [ "$RUNTIME" = kind ]; then
    kind load docker-image vlf:check --name "$CLUSTER"
  else
    k3d image import vlf:check -c "$CLUSTER"
  fi
  # The manifests as they are, in a namespace of their own, with this check's image, secrets
  # and smaller CPU requests (a laptop's cluster has a few cores for four workers).
  cp -r "$ROOT/deploy/k8s" "$WORK/base"
  mkdir "$WORK/overlay"
  cat >"$WORK/overlay/kustomization.yaml" <<EOF
apiVersion: kustomize.config.k8s.io/v1beta1
kind: Kustomization
namespace: $NS
resources: [../base]
images:
  - {name: vlf, newName: vlf, newTag: check}
secretGenerator:
  - name: vlf-secrets
    behavior: replace
    literals:
      - VLF_TOKEN=$VLF_TOKEN
      - AWS_ACCESS_KEY_ID=$AWS_ACCESS_KEY_ID
      - AWS_SECRET_ACCESS_KEY=$AWS_SECRET_ACCESS_KEY
generatorOptions: {disableNameSuffixHash: true}
patches:
  - target: {kind: Deployment, name: vlf-worker}
    patch: |
      - op: replace
        path: /spec/template/spec/containers/0/resources
        value: {requests: {cpu: 250m, memory: 256Mi}, limits: {cpu: "1", memory: 2Gi}}
EOF
  kubectl create namespace "$NS" --dry-run=client -o yaml | kubectl apply -f - >/dev/null
  kubectl apply -k "$WORK/overlay"
  kubectl -n "$NS" wait --for=condition=complete job/vlf-store-bucket --timeout=300s
  kubectl -n "$NS" rollout status deployment/vlf-coordinator --timeout=300s
  kubectl -n "$NS" port-forward service/vlf-coordinator "$PORT:7464" >"$WORK/port-forward.log" 2>&1 &
  FORWARD_PID=$!
  URL=http://127.0.0.1:$PORT
  "$VLF" health --server "$URL" --wait 30 >/dev/null || fail "no coordinator through the port-forward"
  k8s_scale 2
}
k8s_scale() { kubectl -n "$NS" scale deployment/vlf-worker --replicas="$1" >/dev/null; }
k8s_kill_one() {
  local pod
  pod=$(kubectl -n "$NS" get pods -l app.kubernetes.io/component=worker -o name | head -n 1)
  kubectl -n "$NS" delete "$pod" --grace-period=0 --force >/dev/null 2>&1
}
k8s_down() {
  [ -n "${FORWARD_PID:-}" ] && kill "$FORWARD_PID" 2>/dev/null || true
  kubectl delete namespace "$NS" --wait=false >/dev/null 2>&1 || true
  if [ -n "$MADE_CLUSTER" ]; then
    if [ "$RUNTIME" = kind ]; then kind delete cluster --name "$CLUSTER"; else k3d cluster delete "$CLUSTER"; fi
  fi
}

case $RUNTIME in
  local) up=local_up scale=local_scale kill_one=local_kill_one down=local_down ;;
  compose) up=compose_up scale=compose_scale kill_one=compose_kill_one down=compose_down ;;
  kind | k3d) up=k8s_up scale=k8s_scale kill_one=k8s_kill_one down=k8s_down ;;
esac
cleanup() { $down; rm -rf "$WORK"; }
trap cleanup EXIT

# --- the check ---------------------------------------------------------------------------

# The iteration job $JOB is at: its number while it propagates, "end" once it has ended.
iteration() {
  local line
  line=$("$VLF" status "$JOB" --server "$URL")
  case $line in
    *propagating\ iteration*) sed -E 's/.*propagating iteration ([0-9]+).*/\1/' <<<"$line" ;;
    *queued*) echo 0 ;;
    *) echo end ;;
  esac
}
# Waits until the job reaches iteration $1 (or has ended).
reach() {
  local at
  while at=$(iteration) && [ "$at" != end ] && [ "$at" -lt "$1" ]; do sleep 0.2; done
  echo "$at"
}

say "reference: vlf propagate, l = $L, N = $N, $K iterations"
"$VLF" propagate "$SCENE" --store "$WORK/reference" "${SHAPE[@]}" >"$WORK/reference.txt"
expected=$(awk '$1 == "digest" { print $2 }' "$WORK/reference.txt")
[ -n "$expected" ] || fail "no digest in vlf propagate's report: $(cat "$WORK/reference.txt")"

say "$RUNTIME: coordinator, store, two workers"
$up
started=$(date +%s)
JOB=$("$VLF" submit "$SCENE" --server "$URL" "${SHAPE[@]}" | head -n 1)
say "job $JOB submitted"
at=$(reach 2); say "iteration $at: four workers"; $scale 4
at=$(reach 4); say "iteration $at: one killed"; $kill_one
at=$(reach 6); say "iteration $at: one worker"; $scale 1
[ "$at" != end ] || say "the job ended before the last step: use a larger L or N to scale while it runs"
"$VLF" watch "$JOB" --server "$URL" >"$WORK/watch.txt" || fail "the job did not finish: $(tail -n 3 "$WORK/watch.txt")"
got=$("$VLF" status "$JOB" --server "$URL" | sed -nE 's/.*finished, digest ([0-9a-f]+).*/\1/p')
say "finished in $(($(date +%s) - started)) s"
echo "local run: $expected"
echo "$RUNTIME:    ${got:-(none)}"
if [ "$got" = "$expected" ]; then
  echo "the same bits"
else
  echo "DIFFERENT bits" >&2
  exit 1
fi
