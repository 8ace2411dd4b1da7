#!/usr/bin/env bash
# A "second machine" on this one: validator workers in their own network namespace, joined to the
# router over a veth pair, as workers on another host join over the network (no loopback shared).
#
#   sudo deploy/netns_farm.sh up [N]      namespace + veth, then N validators (default 2) connecting
#                                         to tcp/10.200.0.1:7447 (a router must listen there, e.g.
#                                         `gd2p up --validators 0 --listen tcp/10.200.0.1:7447`,
#                                         started after `up` has made the address)
#   sudo deploy/netns_farm.sh net         only the namespace + veth (so the router can bind first)
#   sudo deploy/netns_farm.sh workers [N] only the N validators (the namespace exists)
#   sudo deploy/netns_farm.sh status      the namespace's addresses and its validator processes
#   sudo deploy/netns_farm.sh down        stop the validators, delete the namespace and the veth
#
# Needs root (ip netns). Logs and pids go to $GD2P_FARM_DIR (default /tmp/gd2p-netns-farm).
set -euo pipefail

NS=${GD2P_FARM_NS:-gd2p-farm}
HOST_IF=gd2p-veth0
NS_IF=gd2p-veth1
HOST_ADDR=10.200.0.1
NS_ADDR=10.200.0.2
DIR=${GD2P_FARM_DIR:-/tmp/gd2p-netns-farm}
REPO=$(cd "$(dirname "$0")/.." && pwd)
PYTHON=${PYTHON:-$REPO/.venv/bin/python}

die() { echo "netns_farm: $*" >&2; exit 2; }
[ "$(id -u)" = 0 ] || die "needs root (ip netns add)"

net_up() {
    if ip netns list | grep -qw "$NS"; then echo "namespace $NS exists"; return; fi
    ip netns add "$NS"
    ip link add "$HOST_IF" type veth peer name "$NS_IF"
    ip link set "$NS_IF" netns "$NS"
    ip addr add "$HOST_ADDR/24" dev "$HOST_IF"
    ip link set "$HOST_IF" up
    ip netns exec "$NS" ip addr add "$NS_ADDR/24" dev "$NS_IF"
    ip netns exec "$NS" ip link set "$NS_IF" up
    ip netns exec "$NS" ip link set lo up
    echo "namespace $NS: $NS_ADDR ($NS_IF) <-> host $HOST_ADDR ($HOST_IF)"
}

workers_up() {
    local n=${1:-2}
    ip netns list | grep -qw "$NS" || die "namespace $NS does not exist: run '$0 net' first"
    mkdir -p "$DIR"
    for i in $(seq 1 "$n"); do
        ip netns exec "$NS" env PYTHONPATH="$REPO" "$PYTHON" -m services.validator \
            --connect "tcp/$HOST_ADDR:7447" --worker-id "netns-validator-$i" \
            >"$DIR/validator-$i.log" 2>&1 &
        echo $! >"$DIR/validator-$i.pid"
        echo "validator netns-validator-$i: pid $!, log $DIR/validator-$i.log"
    done
}

down() {
    for pidfile in "$DIR"/validator-*.pid; do
        [ -e "$pidfile" ] || continue
        kill "$(cat "$pidfile")" 2>/dev/null || true
        rm -f "$pidfile"
    done
    ip netns list | grep -qw "$NS" && ip netns del "$NS"
    ip link show "$HOST_IF" >/dev/null 2>&1 && ip link del "$HOST_IF"
    echo "namespace $NS removed"
}

status() {
    ip netns exec "$NS" ip -brief addr
    for pidfile in "$DIR"/validator-*.pid; do
        [ -e "$pidfile" ] || continue
        pid=$(cat "$pidfile")
        if kill -0 "$pid" 2>/dev/null; then
            echo "$(basename "$pidfile" .pid): pid $pid in namespace $(ip netns identify "$pid")"
        else
            echo "$(basename "$pidfile" .pid): pid $pid not running"
        fi
    done
}

case "${1:-}" in
    up) net_up; workers_up "${2:-2}" ;;
    net) net_up ;;
    workers) workers_up "${2:-2}" ;;
    status) status ;;
    down) down ;;
    *) sed -n '2,14p' "$0"; exit 2 ;;
esac
