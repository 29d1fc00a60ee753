#!/usr/bin/env bash
# The Glasshouse compose rig: router, 2 detectors, 3 planners, 4 simulated trolleys, dashboard.
#
#   docker/rig.sh up     build the release binaries, stage stripped copies, make the deployment's
#                        PKI (once) and stage one identity per container, make sure a local base
#                        image exists (debootstrap when debian:bookworm-slim is absent and cannot
#                        be pulled), build the image, start the rig over mutual TLS + ACL
#   docker/rig.sh test   start the rig if needed, wait until every trolley has fruit, run a rogue
#                        container that must get every attempt refused, kill the planner that
#                        owns a trolley, check every trolley keeps getting views and keeps its
#                        fruit, restart that planner and check it rejoins
#   docker/rig.sh down   stop and remove the rig's containers, network and planner stores (the
#                        named volumes; images are kept)
#   docker/rig.sh logs [SERVICE...]   the last 50 log lines of the rig (or of some services)
#
# Environment (all optional):
#   GH_SKIP_BUILD=1        up: do not run cargo; stage what target/<profile> already has
#   GH_PROFILE=dev         up: build and stage the dev profile (target/debug; the algorithm crates
#                          are optimised even there) instead of release: CI reuses the binaries
#                          the tests built rather than compiling the workspace a second time
#   GH_NEW_PKI=1           up: make a new PKI even if docker/.stage/pki exists
#   GH_CARGO_JOBS=N        up: cargo build -j N (default: cargo's own)
#   GH_DEBIAN_MIRROR=URL   debootstrap mirror (default http://deb.debian.org/debian)
#   BASE_IMAGE=IMAGE       use this local base image instead of looking for one
#   GH_HTTP_PORT=8080      host port of the dashboard page + JSON API (also read by compose.yaml)
#   GH_PROMETHEUS_PORT=9091 host port of Prometheus (also read by compose.yaml)
#   GH_FRUIT_TIMEOUT=240   test: seconds to wait until every trolley has at least one fruit
#   GH_FAILOVER_TIMEOUT=30 test: seconds for the failover checks
#   GH_REJOIN_TIMEOUT=90 test: seconds for a restarted planner's first PlannerStatus
#   GH_SETTLE_S=3          test: views reaching the dashboard this soon after the kill don't count
#   GH_VICTIM_TROLLEY=ID   test: the trolley whose owning planner is killed (default: the first)
#   GH_WIDTH, GH_RUST_LOG, GH_RERUN_WEB_PORT, GH_RERUN_GRPC_PORT, GH_PUBLIC_HOST: see compose.yaml
set -euo pipefail

DOCKER_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
REPO="$(cd "$DOCKER_DIR/.." && pwd)"
PROFILE="${GH_PROFILE:-release}"
case "$PROFILE" in
    release) PROFILE_DIR="${CARGO_TARGET_DIR:-$REPO/target}/release" ;;
    dev) PROFILE_DIR="${CARGO_TARGET_DIR:-$REPO/target}/debug" ;;
    *) echo "rig.sh: GH_PROFILE must be release or dev, not $PROFILE" >&2; exit 2 ;;
esac
COMPOSE_FILE="$DOCKER_DIR/compose.yaml"
PROJECT=glasshouse
STAGE="$DOCKER_DIR/.stage"
PKI="$STAGE/pki"
export GH_IDENTITIES="$STAGE/identities"
# Where each container reads its identity (the configs name the files there).
PKI_IN_CONTAINER=/etc/glasshouse/pki
# The containers' user (Dockerfile): the owner of the staged identities, whose keys are 0600.
RIG_UID=10001
# The roster: compose.yaml's services, plus the rogue container's observer (read-only).
ROSTER_ARGS=(--trolleys t1,t2,t3,t4 --planners p1,p2,p3 --detectors d1,d2 --dashboards web1,probe
    --router-hosts router,localhost --router-endpoint tls/router:7447)
# The rogue container: a valid trolley identity (t2) acting on t1's keys, watched by dashboard-probe;
# and the detectors' and planners' identities, each stolen: the one not serving t1 sends it clouds
# and views, the one serving it shows that the same messages from it are taken.
ROGUE_IDENTITIES=(trolley-t2 dashboard-probe detector-d1 detector-d2 planner-p1 planner-p2 planner-p3)
BINS=(glasshouse edge detector-service planner-service dashboard)
SLIM_IMAGE=debian:bookworm-slim
CACHED_BASE=glasshouse-base:bookworm
RIG_IMAGE=glasshouse-rig:latest
MIRROR="${GH_DEBIAN_MIRROR:-http://deb.debian.org/debian}"
export GH_HTTP_PORT="${GH_HTTP_PORT:-8080}"
API="http://127.0.0.1:${GH_HTTP_PORT}"
PROMETHEUS_IMAGE=glasshouse-prometheus:latest
export GH_PROMETHEUS_PORT="${GH_PROMETHEUS_PORT:-9091}"
PROMETHEUS="http://127.0.0.1:${GH_PROMETHEUS_PORT}"
FRUIT_TIMEOUT="${GH_FRUIT_TIMEOUT:-240}"
FAILOVER_TIMEOUT="${GH_FAILOVER_TIMEOUT:-30}"
# Longer than the failover's: a restarted planner restores every map it kept from its store and
# then waits for the fleet to settle, while the survivors may still be moving snapshots of the
# trolleys they took over (on two cores that held every planner's status back for about 30 s
# once; the planners' logs are dumped when it fails).
REJOIN_TIMEOUT="${GH_REJOIN_TIMEOUT:-90}"
SETTLE_S="${GH_SETTLE_S:-3}"
T_START=$(date +%s)

log() { printf '[rig %s +%3ss] %s\n' "$(date +%T)" "$(($(date +%s) - T_START))" "$*" >&2; }

# ---------------------------------------------------------------------------------------------
# docker-compose v1 if present, else the `docker compose` v2 plugin; detected once.
if command -v docker-compose >/dev/null 2>&1; then
    DC=(docker-compose)
elif docker compose version >/dev/null 2>&1; then
    DC=(docker compose)
else
    echo "rig: neither docker-compose nor 'docker compose' is available" >&2
    exit 1
fi
dc() { "${DC[@]}" -p "$PROJECT" -f "$COMPOSE_FILE" "$@"; }

# Prints the last log lines of the given services (all when none are given), then the states.
show_logs() {
    echo "----- ${DC[*]} logs --tail=50 ${*:-(all services)} -----" >&2
    dc logs --no-color --tail=50 "$@" >&2 || true
    echo "----- ${DC[*]} ps -----" >&2
    dc ps >&2 || true
}

# fail MESSAGE [SERVICE...]: logs of the failing services, the message, exit 1.
KILLED_CID=""
fail() {
    local msg="$1"
    shift
    show_logs "$@"
    if [[ -n "$KILLED_CID" ]]; then
        # Leave the rig whole: start the planner the test killed.
        docker start "$KILLED_CID" >/dev/null 2>&1 && log "restarted the killed container ${KILLED_CID:0:12}"
    fi
    log "FAIL: $msg"
    exit 1
}

# ---------------------------------------------------------------------------------------------
# up

build_binaries() {
    if [[ "${GH_SKIP_BUILD:-0}" == 1 ]]; then
        log "GH_SKIP_BUILD=1: not running cargo"
        return
    fi
    local t0=$SECONDS
    log "cargo build --profile $PROFILE --workspace --bins ${GH_CARGO_JOBS:+-j $GH_CARGO_JOBS}"
    (cd "$REPO" && cargo build --locked --profile "$PROFILE" --workspace --bins ${GH_CARGO_JOBS:+-j "$GH_CARGO_JOBS"})
    log "binaries built in $((SECONDS - t0)) s"
}

# Stripped copies in docker/.stage/bin; target/ is never touched.
stage_binaries() {
    local b
    rm -rf "$STAGE/bin.new"
    mkdir -p "$STAGE/bin.new"
    for b in "${BINS[@]}"; do
        [[ -x "$PROFILE_DIR/$b" ]] ||
            fail "$PROFILE_DIR/$b is missing (run without GH_SKIP_BUILD=1)"
        strip --strip-all -o "$STAGE/bin.new/$b" "$PROFILE_DIR/$b"
    done
    rm -rf "${STAGE:?}/bin"
    mv "$STAGE/bin.new" "$STAGE/bin"
    log "staged stripped binaries: $(du -sh "$STAGE/bin" | cut -f1) in docker/.stage/bin"
}

# The deployment's PKI (CA, router, one identity per process, router.json5 with the ACL), made
# once with `glasshouse secure init`; ca.key stays in docker/.stage/pki, never in a container.
make_pki() {
    if [[ -f "$PKI/ca.key" && "${GH_NEW_PKI:-0}" != 1 ]]; then
        log "PKI: docker/.stage/pki exists (GH_NEW_PKI=1 makes a new one)"
        return
    fi
    as_root rm -rf "$PKI"
    "$STAGE/bin/glasshouse" secure init --out "$PKI" "${ROSTER_ARGS[@]}" \
        --install-dir "$PKI_IN_CONTAINER" >/dev/null || fail "secure init failed"
    log "PKI: made docker/.stage/pki (glasshouse secure init ${ROSTER_ARGS[*]})"
}

# stage_identity DIR NAME...: the CA certificate and each NAME's key, certificate and config.
stage_identity() {
    local dir="$1" name
    shift
    mkdir -p "$dir"
    cp "$PKI/ca.pem" "$dir/"
    for name in "$@"; do
        cp "$PKI/$name.key" "$PKI/$name.pem" "$PKI/$name.json5" "$dir/" ||
            fail "the PKI has no identity $name (GH_NEW_PKI=1 makes a new one)"
    done
}

# docker/.stage/identities/<name>/: what one container mounts, owned by the containers' user.
stage_identities() {
    local ids=() f name
    as_root rm -rf "$GH_IDENTITIES"
    for f in "$PKI"/*.json5; do
        name="$(basename "$f" .json5)"
        [[ "$name" == roster ]] || ids+=("$name")
    done
    for name in "${ids[@]}"; do stage_identity "$GH_IDENTITIES/$name" "$name"; done
    stage_identity "$GH_IDENTITIES/rogue" "${ROGUE_IDENTITIES[@]}"
    as_root chown -R "$RIG_UID:$RIG_UID" "$GH_IDENTITIES"
    log "identities staged: ${ids[*]} (+ rogue: ${ROGUE_IDENTITIES[*]})"
}

as_root() {
    if [[ $EUID -eq 0 ]]; then "$@"; else sudo "$@"; fi
}

# Builds glasshouse-base:bookworm from a debootstrap minbase rootfs (no registry needed).
make_base_image() {
    local t0=$SECONDS dir
    if ! command -v debootstrap >/dev/null 2>&1; then
        log "installing debootstrap"
        as_root apt-get update -qq
        as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq debootstrap >/dev/null
    fi
    dir="$(mktemp -d /var/tmp/glasshouse-rootfs.XXXXXX)"
    log "debootstrap --variant=minbase bookworm $dir $MIRROR"
    if ! as_root debootstrap --variant=minbase bookworm "$dir" "$MIRROR" >"$dir.log" 2>&1; then
        tail -20 "$dir.log" >&2
        as_root rm -rf "$dir" "$dir.log"
        fail "debootstrap failed"
    fi
    as_root rm -rf "$dir"/var/cache/apt/archives/*.deb "$dir"/var/lib/apt/lists/* \
        "$dir"/usr/share/doc/* "$dir"/usr/share/man/* "$dir"/usr/share/locale/*
    log "docker import -> $CACHED_BASE"
    as_root tar -C "$dir" -c . | docker import \
        --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
        --change 'CMD ["/bin/bash"]' - "$CACHED_BASE" >/dev/null
    as_root rm -rf "$dir" "$dir.log"
    log "base image $CACHED_BASE made in $((SECONDS - t0)) s"
}

# Sets BASE_IMAGE to a base image that is in the local store.
ensure_base_image() {
    if [[ -n "${BASE_IMAGE:-}" ]]; then
        docker image inspect "$BASE_IMAGE" >/dev/null 2>&1 ||
            fail "BASE_IMAGE=$BASE_IMAGE is not in the local image store"
    elif docker image inspect "$SLIM_IMAGE" >/dev/null 2>&1; then
        BASE_IMAGE=$SLIM_IMAGE
    elif docker image inspect "$CACHED_BASE" >/dev/null 2>&1; then
        BASE_IMAGE=$CACHED_BASE
    elif timeout 60 docker pull -q "$SLIM_IMAGE" >/dev/null 2>&1; then
        BASE_IMAGE=$SLIM_IMAGE
    else
        log "$SLIM_IMAGE is not local and cannot be pulled: building $CACHED_BASE"
        make_base_image
        BASE_IMAGE=$CACHED_BASE
    fi
    export BASE_IMAGE
    log "base image: $BASE_IMAGE"
}

cmd_up() {
    build_binaries
    stage_binaries
    make_pki
    stage_identities
    ensure_base_image
    local t0=$SECONDS
    # Plain `docker build` (what compose.yaml's router `build:` section describes): it works with
    # the legacy builder and with BuildKit, whereas compose v2 needs buildx to build.
    log "building $RIG_IMAGE from $BASE_IMAGE (docker build)"
    docker build --build-arg "BASE_IMAGE=$BASE_IMAGE" -t "$RIG_IMAGE" -f "$DOCKER_DIR/Dockerfile" \
        "$DOCKER_DIR" || fail "image build failed"
    log "building $PROMETHEUS_IMAGE from $BASE_IMAGE (Debian's prometheus package)"
    docker build -q --build-arg "BASE_IMAGE=$BASE_IMAGE" -t "$PROMETHEUS_IMAGE" \
        "$DOCKER_DIR/prometheus" >/dev/null || fail "Prometheus image build failed"
    # The previous images (now untagged) only hold older binaries.
    docker image prune -f --filter label=org.glasshouse.rig=1 >/dev/null || true
    log "image built in $((SECONDS - t0)) s ($(docker image inspect -f '{{.Size}}' "$RIG_IMAGE" |
        awk '{printf "%.0f MB", $1 / 1e6}'))"
    t0=$SECONDS
    dc up -d --no-build --remove-orphans || fail "${DC[*]} up failed"
    log "rig started in $((SECONDS - t0)) s; dashboard: http://localhost:$GH_HTTP_PORT/"
}

cmd_down() {
    # docker-compose v1 removes the network right after the containers; the daemon sometimes
    # keeps an endpoint of a removed container ("network ... has active endpoints", with no
    # container left on it) and compose stops there, before the volumes. The containers are
    # gone by then and a later `up` attaches to the same network as it is, so the volumes are
    # removed here, and the network is waited for a while and otherwise left with a warning.
    if ! dc down --remove-orphans --volumes; then
        if [[ -n "$(dc ps -q)" ]]; then
            echo "${DC[*]} down left containers behind" >&2
            return 1
        fi
        docker volume ls -q --filter "label=com.docker.compose.project=$PROJECT" \
            | xargs -r docker volume rm >/dev/null || return 1
        local network="${PROJECT}_default" deadline=$((SECONDS + 30))
        until docker network rm "$network" >/dev/null 2>&1 \
            || ! docker network inspect "$network" >/dev/null 2>&1; do
            if ((SECONDS >= deadline)); then
                local attached
                attached="$(docker network inspect -f '{{range .Containers}}{{.Name}} {{end}}' "$network")"
                if [[ -n "$attached" ]]; then
                    echo "network $network still has containers on it: $attached" >&2
                    return 1
                fi
                log "warning: network $network kept by a stale endpoint of the daemon; no container or volume is left, and the next up reuses it"
                return 0
            fi
            sleep 1
        done
    fi
    log "rig removed (images kept)"
}

# ---------------------------------------------------------------------------------------------
# test helpers: containers (found by their compose labels, which v1 and v2 both set)

# Services of the compose file that have a running container.
running_services() {
    docker ps --filter "label=com.docker.compose.project=$PROJECT" \
        --format '{{.Label "com.docker.compose.service"}}' | sort -u
}

# True when every service of the compose file has a running container.
rig_running() {
    local want have
    want="$(dc config --services | sort -u)"
    have="$(running_services)"
    [[ -n "$want" && "$want" == "$have" ]]
}

# Container id of a compose service: `ps -q SERVICE` (first replica; -a: stopped ones too).
cid_of() { dc ps -a -q "$1" | head -n1; }

running() { [[ "$(docker inspect -f '{{.State.Running}}' "$1" 2>/dev/null)" == true ]]; }

declare -A TROLLEY_SVC=() PLANNER_SVC=() PLANNER_CID=()
LIVE_PLANNERS=()
# Maps trolley and planner ids to compose services, from the containers' own command lines
# (--trolley-id / --planner-id), so nothing here hard-codes ids or container names.
map_services() {
    local svc cid kind id
    while read -r svc cid kind id; do
        case "$kind" in
            --trolley-id) TROLLEY_SVC[$id]=$svc ;;
            --planner-id) PLANNER_SVC[$id]=$svc PLANNER_CID[$id]=$cid ;;
        esac
    done < <(docker ps -a -q --filter "label=com.docker.compose.project=$PROJECT" |
        xargs -r docker inspect -f \
            '{{index .Config.Labels "com.docker.compose.service"}} {{.Id}}{{range .Args}} {{.}}{{end}}' |
        awk '{ for (i = 3; i < NF; i++) if ($i == "--trolley-id" || $i == "--planner-id") print $1, $2, $i, $(i + 1) }')
    [[ ${#TROLLEY_SVC[@]} -gt 0 ]] || fail "no trolley services found"
    [[ ${#PLANNER_SVC[@]} -gt 0 ]] || fail "no planner services found"
}

live_planners() {
    local pid
    LIVE_PLANNERS=()
    for pid in "${!PLANNER_CID[@]}"; do
        running "${PLANNER_CID[$pid]}" && LIVE_PLANNERS+=("$pid")
    done
    return 0
}

# ---------------------------------------------------------------------------------------------
# test helpers: the dashboard JSON API

# load_fleet: GET /api/fleet into T_* (per trolley) and P_* (per planner) arrays (P_ROW: the
# planner's row as one string, without P_AGE = last_status_age_s, "-" when the dashboard does
# not report it), plus one-line
# summaries FLEET_LINE and PLANNER_LINE. Returns 1 when the dashboard does not answer.
# Prints bash assignments (values shell-quoted) from the fleet document on stdin.
read -r -d '' FLEET_PY <<'PY' || true
import json, shlex, sys
q = shlex.quote
doc = json.load(sys.stdin)
line = []
for t in doc['trolleys']:
    i = q(t['id'])
    print(f"T_FRUITS[{i}]={t['fruits']} T_VIEWS[{i}]={t['views_done']} T_FRAMES[{i}]={t['frames']}"
          f" T_PLANNER[{i}]={q(t['planner'] or '-')} T_STATE[{i}]={q(t['state'])}")
    line.append(f"{t['id']}:{t['fruits']} fruits/{t['views_done']} views/{t['planner'] or '-'}")
print("FLEET_LINE=" + q("  ".join(line)))
line = []
for p in doc['planners']:
    i = q(p['id'])
    owned, standby = ",".join(p['owned']) or "-", ",".join(p['standby']) or "-"
    row = (f"owned={owned} standby={standby} clouds={p['clouds_integrated']}"
           f" views={p['views_published']} voxels={p['map_voxels']}")
    age = p.get('last_status_age_s')
    age = '-' if age is None else f"{age:.1f}"
    print(f"P_OWNED[{i}]={q(owned)} P_ROW[{i}]={q(row)} P_AGE[{i}]={q(age)}")
    line.append(f"{p['id']} {row}" + ("" if age == '-' else f" status_age={age}s"))
print("PLANNER_LINE=" + q("  |  ".join(line)))
PY
declare -A T_FRUITS=() T_VIEWS=() T_FRAMES=() T_PLANNER=() T_STATE=() P_OWNED=() P_ROW=() P_AGE=()
FLEET_LINE="" PLANNER_LINE=""
load_fleet() {
    local json out
    json="$(curl -fsS --max-time 5 "$API/api/fleet" 2>/dev/null)" || return 1
    out="$(python3 -c "$FLEET_PY" <<<"$json")" || return 1
    T_FRUITS=() T_VIEWS=() T_FRAMES=() T_PLANNER=() T_STATE=() P_OWNED=() P_ROW=() P_AGE=()
    eval "$out"
}

# Number of fruits /api/trolleys/{id}/fruits lists (empty when the trolley is unknown).
fruit_count() {
    curl -fsS --max-time 5 "$API/api/trolleys/$1/fruits" 2>/dev/null |
        python3 -c 'import json, sys; print(len(json.load(sys.stdin)))' 2>/dev/null || true
}

# ---------------------------------------------------------------------------------------------
# owner_of TID: which planner owns a trolley, from the state load_fleet read. Kept in one place
# so it can follow the planner cluster as it grows. Order:
#   1. the one live planner whose PlannerStatus lists TID in `owned` (PlannerRow.owned);
#   2. when none or several do (today every planner plans for every trolley, so all of them
#      "own" it), the planner_id of the trolley's latest RankedViews (TrolleyRow.planner).
# Sets OWNER and OWNER_HOW. Dead planners (stopped containers) are skipped via LIVE_PLANNERS.
owner_of() {
    local tid="$1" claims=() pid
    for pid in "${LIVE_PLANNERS[@]}"; do
        [[ ",${P_OWNED[$pid]:-}," == *",$tid,"* ]] && claims+=("$pid")
    done
    if [[ ${#claims[@]} -eq 1 ]]; then
        OWNER="${claims[0]}" OWNER_HOW="PlannerStatus.owned"
    else
        OWNER="${T_PLANNER[$tid]:--}"
        OWNER_HOW="planner_id of its latest views (${#claims[@]} live planners claim it: ${claims[*]:-none})"
    fi
}

# ---------------------------------------------------------------------------------------------
# run_rogue TID...: `glasshouse secure probe` in a container of its own on the rig's network, as
# trolley-t2 acting on t1's keys (and without a certificate, and with another CA's), and as a
# compromised detector and planner sending t1 clouds and views, watched by dashboard-probe. Fails
# unless every attempt is refused and every trolley still gets views.
ROGUE_LINE=""
run_rogue() {
    local tids=("$@") network out t0=$SECONDS tid
    network="$(docker inspect -f '{{range $k, $v := .NetworkSettings.Networks}}{{$k}} {{end}}' \
        "$(cid_of router)" | awk '{print $1}')"
    [[ -n "$network" ]] || fail "cannot tell the rig's network" router
    load_fleet || fail "the dashboard API does not answer" dashboard
    declare -A views_before=()
    for tid in "${tids[@]}"; do views_before[$tid]="${T_VIEWS[$tid]:-0}"; done
    # Up to three tries, each against another victim (never t2, the rogue's own identity): in a
    # fleet still settling, the detector a planner takes a trolley's clouds from can change under
    # the probe (seen twice: a compromised detector's cloud "accepted" while it was the one the
    # owner took clouds from; the probe now takes as serving only a detector whose frame the
    # victim's map has taken), and a probe whose control cannot reach the victim's arm (seen twice in one run: every
    # view of t1 out of reach, its control views refused or never executed) cannot judge. The
    # holes it looks for are the identities' and the ACL's, the same for every trolley: a real
    # hole fails every try. Each failed try logs every trolley's state.
    local try victim victims=()
    for tid in t1 t3 t4; do [[ -n "${views_before[$tid]+set}" ]] && victims+=("$tid"); done
    ((${#victims[@]} > 0)) || victims=(t1)
    for try in "${!victims[@]}"; do
        victim="${victims[$try]}"
        log "rogue: glasshouse secure probe on network $network as trolley-t2 against $victim"
        if out="$(docker run --rm --network "$network" --init \
            -v "$GH_IDENTITIES/rogue:$PKI_IN_CONTAINER:ro" "$RIG_IMAGE" \
            glasshouse secure probe --rogue "$PKI_IN_CONTAINER/trolley-t2.json5" \
            --observer "$PKI_IN_CONTAINER/dashboard-probe.json5" --victim "$victim" --planners p1,p2,p3 \
            --detector-identity "$PKI_IN_CONTAINER/detector-d1.json5,$PKI_IN_CONTAINER/detector-d2.json5" \
            --planner-identity "$PKI_IN_CONTAINER/planner-p1.json5,$PKI_IN_CONTAINER/planner-p2.json5,$PKI_IN_CONTAINER/planner-p3.json5" \
            2>&1)"; then
            break
        fi
        printf '%s\n' "$out" >&2
        if load_fleet; then
            for tid in "${tids[@]}"; do
                log "  $tid: state ${T_STATE[$tid]:-?}, ${T_VIEWS[$tid]:-?} views, ${T_FRAMES[$tid]:-?} frames, views from ${T_PLANNER[$tid]:--}"
            done
        fi
        ((try + 1 < ${#victims[@]})) ||
            fail "the rogue container was not refused everything (or could not judge), ${#victims[@]} tries" router
        log "rogue: try $((try + 1)) against $victim failed (above); trying against another trolley"
    done
    printf '%s\n' "$out" | sed 's/^/    /' >&2
    ROGUE_LINE="$(printf '%s\n' "$out" | tail -n1) in $((SECONDS - t0)) s"
    # The legitimate fleet keeps running: every trolley gets new views after the probe.
    local pending=("${tids[@]}") still t1=$SECONDS
    while ((${#pending[@]} > 0)); do
        ((SECONDS - t1 < FAILOVER_TIMEOUT)) ||
            fail "after the rogue, no new views within ${FAILOVER_TIMEOUT} s for: ${pending[*]}" dashboard
        sleep 1
        load_fleet || continue
        still=()
        for tid in "${pending[@]}"; do
            [[ "${T_VIEWS[$tid]:-0}" -gt "${views_before[$tid]}" || "${T_STATE[$tid]:-}" == Done ]] ||
                still+=("$tid")
        done
        pending=("${still[@]}")
    done
    log "rogue: $ROGUE_LINE; every trolley got new views after it"
}

# Every scrape target up; then every query of docker/grafana/glasshouse-dashboard.json answers
# with at least one series (rates need two scrapes: the check retries for up to a minute).
PROMETHEUS_TARGETS_PY='
import json, sys
targets = json.load(sys.stdin)["data"]["activeTargets"]
down = sorted(t["labels"]["instance"] for t in targets if t["health"] != "up")
print(f"{len(targets) - len(down)} of {len(targets)} targets up" + (f"; down: {down}" if down else ""))
sys.exit(1 if down or not targets else 0)'
PROMETHEUS_PANELS_PY='
import json, sys, urllib.parse, urllib.request
base, dashboard = sys.argv[1], sys.argv[2]
empty = []
panels = json.load(open(dashboard))["panels"]
for panel in panels:
    for target in panel["targets"]:
        url = base + "/api/v1/query?" + urllib.parse.urlencode({"query": target["expr"]})
        result = json.load(urllib.request.urlopen(url, timeout=5))["data"]["result"]
        if not result:
            empty.append(panel["title"])
print(f"{len(panels) - len(empty)} of {len(panels)} dashboard panels have data" + (f"; empty: {empty}" if empty else ""))
sys.exit(1 if empty else 0)'

check_prometheus() {
    local t0=$SECONDS out=""
    log "waiting up to 90 s until Prometheus scrapes every service and the dashboard's panels have data"
    until out="$(curl -fsS --max-time 5 "$PROMETHEUS/api/v1/targets" 2>/dev/null |
        python3 -c "$PROMETHEUS_TARGETS_PY" 2>&1)"; do
        ((SECONDS - t0 < 90)) || fail "Prometheus: ${out:-no answer from $PROMETHEUS}" prometheus
        sleep 2
    done
    log "  Prometheus: $out after $((SECONDS - t0)) s"
    until out="$(python3 -c "$PROMETHEUS_PANELS_PY" "$PROMETHEUS" \
        "$DOCKER_DIR/grafana/glasshouse-dashboard.json" 2>&1)"; do
        ((SECONDS - t0 < 90)) || fail "Grafana dashboard: $out" prometheus
        sleep 2
    done
    log "  $out after $((SECONDS - t0)) s"
}

cmd_test() {
    local t_test=$SECONDS
    # Any unexpected error during the test also shows the logs.
    set -o errtrace
    trap 'fail "unexpected error (exit $?) at rig.sh line $LINENO"' ERR
    if rig_running; then
        log "rig is running"
    else
        log "rig is not (fully) running: up"
        cmd_up
    fi
    map_services
    local tids=() tid pid
    mapfile -t tids < <(printf '%s\n' "${!TROLLEY_SVC[@]}" | sort)
    local planner_svcs=()
    for pid in "${!PLANNER_SVC[@]}"; do planner_svcs+=("${PLANNER_SVC[$pid]}"); done
    log "trolleys: $(for t in "${tids[@]}"; do printf '%s=%s ' "$t" "${TROLLEY_SVC[$t]}"; done)"
    log "planners: $(for p in $(printf '%s\n' "${!PLANNER_SVC[@]}" | sort); do printf '%s=%s ' "$p" "${PLANNER_SVC[$p]}"; done)"

    # 1. Every trolley has at least one fruit (fleet counts, confirmed by the fruits endpoint).
    local t0=$SECONDS missing last_print=-100 line
    log "waiting up to ${FRUIT_TIMEOUT} s until every trolley has a fruit ($API/api/fleet)"
    while :; do
        missing=()
        if load_fleet; then
            line="$FLEET_LINE"
            for tid in "${tids[@]}"; do
                [[ "${T_FRUITS[$tid]:-0}" -ge 1 ]] || missing+=("$tid")
            done
            if [[ ${#missing[@]} -eq 0 ]]; then
                for tid in "${tids[@]}"; do
                    [[ "$(fruit_count "$tid")" -ge 1 ]] 2>/dev/null || missing+=("$tid")
                done
                [[ ${#missing[@]} -eq 0 ]] && break
            fi
        else
            missing=("${tids[@]}") line="dashboard API not answering yet"
        fi
        if ((SECONDS - t0 >= FRUIT_TIMEOUT)); then
            local failing=(dashboard)
            for tid in "${missing[@]}"; do failing+=("${TROLLEY_SVC[$tid]}"); done
            fail "after ${FRUIT_TIMEOUT} s these trolleys still have no fruit: ${missing[*]} ($line)" \
                "${failing[@]}" "${planner_svcs[@]}"
        fi
        if ((SECONDS - last_print >= 10)); then
            log "  $((SECONDS - t0)) s: $line"
            last_print=$SECONDS
        fi
        sleep 1
    done
    local t_fruits=$((SECONDS - t0))
    log "every trolley has fruit after ${t_fruits} s: $FLEET_LINE"
    log "planners: $PLANNER_LINE"

    # 1b. Prometheus scrapes every service, and every panel of the Grafana dashboard has data.
    check_prometheus

    # 2. A rogue container on the rig's network: every attempt must be refused, the fleet goes on.
    run_rogue "${tids[@]}"

    # 3. Kill the planner that owns the victim trolley; every trolley must keep getting views.
    local victim="${GH_VICTIM_TROLLEY:-${tids[0]}}"
    [[ -n "${TROLLEY_SVC[$victim]:-}" ]] || fail "GH_VICTIM_TROLLEY=$victim is not a trolley of the rig"
    live_planners
    owner_of "$victim"
    local owner="$OWNER" how="$OWNER_HOW"
    [[ -n "${PLANNER_SVC[$owner]:-}" ]] ||
        fail "cannot tell which planner owns $victim (lookup gave '$owner' via $how)" dashboard "${planner_svcs[@]}"
    local psvc="${PLANNER_SVC[$owner]}" pcid
    pcid="$(cid_of "$psvc")"
    [[ -n "$pcid" ]] || fail "no container for service $psvc"
    log "owner of $victim: $owner via $how -> service $psvc, container ${pcid:0:12}"

    declare -A views0=() views1=() fruits0=() frames0=() first_view=()
    for tid in "${tids[@]}"; do
        views0[$tid]="${T_VIEWS[$tid]}" fruits0[$tid]="${T_FRUITS[$tid]}" frames0[$tid]="${T_FRAMES[$tid]}"
    done
    docker kill "$pcid" >/dev/null
    KILLED_CID=$pcid
    local t_kill=$SECONDS takeover="" new_owner="" pending=("${tids[@]}") still settled=0
    log "killed $psvc ($owner); every trolley must get a new view within ${FAILOVER_TIMEOUT} s"
    live_planners
    while :; do
        sleep 0.5
        load_fleet || continue
        # Takeover observations (reported, not required): the victim's views come from another
        # planner; a live planner's PlannerStatus names itself the victim's single owner.
        if [[ -z "$takeover" && "${T_PLANNER[$victim]:--}" != "$owner" && "${T_PLANNER[$victim]:--}" != - ]]; then
            takeover="views for $victim from ${T_PLANNER[$victim]} after $((SECONDS - t_kill)) s"
        fi
        if [[ -z "$new_owner" ]]; then
            owner_of "$victim"
            [[ "$OWNER_HOW" == PlannerStatus.owned ]] &&
                new_owner="$OWNER owns $victim (PlannerStatus.owned) after $((SECONDS - t_kill)) s"
        fi
        # The dashboard lags the fleet by a second or two, so views the killed planner sent
        # before it died still arrive after the kill. Count only views that arrive after
        # SETTLE_S and whose sender (the trolley's latest views) is not the killed planner.
        if ((settled == 0)); then
            ((SECONDS - t_kill >= SETTLE_S)) || continue
            for tid in "${tids[@]}"; do views1[$tid]="${T_VIEWS[$tid]:-0}"; done
            settled=1
            continue
        fi
        still=()
        for tid in "${pending[@]}"; do
            if [[ "${T_VIEWS[$tid]:-0}" -gt "${views1[$tid]}" && "${T_PLANNER[$tid]:--}" != "$owner" &&
                "${T_FRUITS[$tid]:-0}" -ge 1 ]]; then
                first_view[$tid]=$((SECONDS - t_kill))
            else
                still+=("$tid")
            fi
        done
        pending=("${still[@]}")
        [[ ${#pending[@]} -eq 0 && -n "$takeover" && -n "$new_owner" ]] && break
        if ((SECONDS - t_kill >= FAILOVER_TIMEOUT)); then
            [[ ${#pending[@]} -eq 0 ]] && break
            local failing=(dashboard) detail=""
            for tid in "${pending[@]}"; do
                failing+=("${TROLLEY_SVC[$tid]}")
                # Frames growing without views = the trolley re-announces and nobody answers;
                # state Done = it finished its row (the edge then exits).
                detail+=" $tid: state ${T_STATE[$tid]:-?}, views ${views0[$tid]} -> ${views1[$tid]:-?} (+${SETTLE_S} s) -> ${T_VIEWS[$tid]:-?} (latest from ${T_PLANNER[$tid]:-?}), frames ${frames0[$tid]} -> ${T_FRAMES[$tid]:-?}, fruits ${T_FRUITS[$tid]:-?};"
            done
            fail "after killing $owner, no new view within ${FAILOVER_TIMEOUT} s for: ${pending[*]} ($detail)" \
                "${failing[@]}" "${planner_svcs[@]}"
        fi
    done
    local t_failover=$((SECONDS - t_kill)) fruits_after_failover="${T_FRUITS[$victim]:-?}"
    for tid in "${tids[@]}"; do
        log "  $tid: views ${views0[$tid]} -> ${views1[$tid]} (at +${SETTLE_S} s) -> ${T_VIEWS[$tid]} (first counted one after ${first_view[$tid]} s), fruits ${fruits0[$tid]} -> ${T_FRUITS[$tid]}, latest views from ${T_PLANNER[$tid]}"
    done
    log "  takeover: ${takeover:-not seen: $victim got no views from another planner within ${FAILOVER_TIMEOUT} s}"
    log "  ownership: ${new_owner:-no single live planner lists $victim in PlannerStatus.owned}"
    log "  planners: $PLANNER_LINE"
    running "$pcid" && log "  note: docker restarted $psvc by itself (restart policy)"

    # 4. Restart the killed planner. It has rejoined when the dashboard gets a new PlannerStatus
    #    from it: the dashboard keeps a dead planner's last row, so wait for that row to change.
    local frozen="${P_ROW[$owner]:-}"
    docker start "$pcid" >/dev/null
    KILLED_CID=""
    local t_restart=$SECONDS
    log "restarted $psvc; its PlannerStatus ($owner) must come back within ${REJOIN_TIMEOUT} s"
    while :; do
        sleep 0.5
        if load_fleet && [[ -n "${P_ROW[$owner]:-}" && "${P_ROW[$owner]}" != "$frozen" ]]; then
            break
        fi
        ((SECONDS - t_restart < REJOIN_TIMEOUT)) ||
            fail "$owner sent no new PlannerStatus within ${REJOIN_TIMEOUT} s of its restart (row: ${P_ROW[$owner]:-none}; planners: $PLANNER_LINE)" \
                "${planner_svcs[@]}" dashboard router
    done
    local t_rejoin=$((SECONDS - t_restart))
    log "  $owner is back after ${t_rejoin} s: ${P_ROW[$owner]} last_status_age_s=${P_AGE[$owner]:--}"
    # Reported, not required: whether the rejoined planner takes its trolley back.
    live_planners
    local back="" t_back=$SECONDS
    while ((SECONDS - t_back < FAILOVER_TIMEOUT)); do
        if load_fleet; then
            owner_of "$victim"
            if [[ "$OWNER" == "$owner" && "$OWNER_HOW" == PlannerStatus.owned ]]; then
                back="$owner owns $victim again $((SECONDS - t_restart)) s after its restart"
                break
            fi
        fi
        sleep 0.5
    done
    log "  owner of $victim now: $OWNER via $OWNER_HOW${back:+ ($back)}"
    local fruits_back="${T_FRUITS[$victim]:-?}"
    log "  fruits of $victim: ${fruits0[$victim]} before the kill, $fruits_after_failover after the failover, $fruits_back now"

    echo
    echo "rig test PASSED (${DC[*]}, project $PROJECT)"
    printf '  %-34s %s\n' \
        "every trolley had fruit after" "${t_fruits} s (${#tids[@]} trolleys; limit ${FRUIT_TIMEOUT} s)" \
        "rogue container (mTLS + ACL)" "$ROGUE_LINE" \
        "killed planner" "$owner ($psvc), owner of $victim via $how" \
        "every trolley had a new view after" "${t_failover} s (limit ${FAILOVER_TIMEOUT} s)" \
        "takeover (views)" "${takeover:-not observed}" \
        "takeover (ownership)" "${new_owner:-not observed}" \
        "$owner rejoined after" "${t_rejoin} s (limit ${FAILOVER_TIMEOUT} s)" \
        "ownership after the rejoin" "${back:-$victim stays with $OWNER (via $OWNER_HOW)}" \
        "fruits of $victim" "${fruits0[$victim]} before the kill, $fruits_after_failover after the failover, $fruits_back at the end" \
        "test total" "$((SECONDS - t_test)) s"
}

case "${1:-}" in
    up) cmd_up ;;
    down) cmd_down ;;
    test) cmd_test ;;
    logs) shift; dc logs --no-color --tail=50 "$@" ;;
    *)
        echo "usage: $0 up|test|down|logs [SERVICE...]" >&2
        exit 2
        ;;
esac
