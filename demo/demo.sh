#!/usr/bin/env bash
# `make demo [FAULT=leak|flood|throttle|leak,flood,...|all]` and `make demo-stop`: a small robot on this machine,
# watched by Drums as an operator would watch it.
#
# Two "computers": the camera's (a network namespace, reached over a veth link) and the main one
# (this host), where the processor, controller and logger run. Their ROS 2 nodes talk over UDP.
# On the main computer: the Drums agent (http://127.0.0.1:19969/), Prometheus with the mixin's
# rules and alerts (http://127.0.0.1:19090/alerts), and `drums top` in front when there is a
# terminal. Ports of their own, so that a Drums or Prometheus already running is left alone.
#
# FAULT injects one of the three faults of the paper that started Drums, or several at once
# (comma-separated), 20 s after the start (throttle after 60 s, once the camera's link has carried a
# minute of images to compare with):
#   leak      the processor keeps one image in ten: its memory grows by about 3 MB/s, to 1 GiB
#             (DrumsNodeMemoryLeak on /processor fires within a minute)
#   flood     the logger logs to /rosout in a tight loop (DrumsTopicFlooding on /logger, /rosout;
#             its subscription starves: DrumsTopicMessagesLost on /detections)
#   throttle  the camera computer's link drops to 4 Mbit/s (a faulty router): /camera/image
#             collapses and is repaired over and over (DrumsEdgeRetransmitsHigh on /camera ->
#             /processor within two minutes; DrumsEdgeBandwidthCollapsed needs an hour of history)
#   all       the three in turn, each for a while: the leak at $DRUMS_DEMO_FAULT_AFTER s (default 150,
#             after the nodes' first 2 minutes, which the detector leaves alone) for 20 s, the flood
#             40 s later for 20 s, the throttle 40 s after that for 30 s
#
# `drums detect` watches the agent too (http://127.0.0.1:19971/anomalies, its events in
# .demo/detect.jsonl): each fault is named there within seconds, on its node, topic or edge.
#
# `make demo-stop` ends all of it and leaves nothing behind: processes, BPF pins, the namespace.
set -euo pipefail
cd "$(dirname "$0")/.."

STATE=.demo
NS=drums-demo-camera
LINK=drumsdemo  # drumsdemo0 here, drumsdemo1 on the camera computer
PINS=/sys/fs/bpf/drums-demo
AGENT_PORT=${DRUMS_DEMO_AGENT_PORT:-19969}  # each port can be moved by its variable
STREAM_PORT=${DRUMS_DEMO_STREAM_PORT:-19970}
PROMETHEUS_PORT=${DRUMS_DEMO_PROMETHEUS_PORT:-19090}
DETECT_PORT=${DRUMS_DEMO_DETECT_PORT:-19971}
PY=.venv/bin/python
FAULT_AFTER=${DRUMS_DEMO_FAULT_AFTER:-20}
THROTTLE_AFTER=60
export ROS_DOMAIN_ID=201 FASTDDS_BUILTIN_TRANSPORTS=UDPv4 ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET \
  ROS_STATIC_PEERS="10.77.0.1;10.77.0.2"

say() { echo "demo: $*" >&2; }

# Runs a program in the background, its output in $STATE/<name>.log and its PID in $STATE/<name>.pid.
spawn() {
  local name=$1
  shift
  setsid "$@" >"$STATE/$name.log" 2>&1 </dev/null &
  echo $! >"$STATE/$name.pid"
}

stop() {
  local pidfile pid
  for pidfile in "$STATE"/*.pid; do
    [ -e "$pidfile" ] || continue
    pid=$(cat "$pidfile")
    kill -TERM -- "-$pid" 2>/dev/null || true  # its whole process group (setsid)
  done
  for pidfile in "$STATE"/*.pid; do
    [ -e "$pidfile" ] || continue
    pid=$(cat "$pidfile")
    for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
    kill -KILL -- "-$pid" 2>/dev/null || true
    rm -f "$pidfile"
  done
  [ -d "$PINS" ] && .venv/bin/drums unload --pin-dir "$PINS" >/dev/null
  ip netns del "$NS" 2>/dev/null || true
  ip link del "${LINK}0" 2>/dev/null || true
  rm -rf "$STATE"
}

wait_for() {  # NAME URL: until the URL answers 200 while NAME runs, 60 s at most
  for _ in $(seq 300); do
    if ! kill -0 "$(cat "$STATE/$1.pid")" 2>/dev/null; then
      say "$1 did not start: $(tail -n 1 "$STATE/$1.log")"
      stop
      exit 1
    fi
    "$PY" -c 'import sys, urllib.request; urllib.request.urlopen(sys.argv[1], timeout=1)' "$2" 2>/dev/null && return 0
    sleep 0.2
  done
  say "$1 did not answer at $2 within 60 s: see $STATE/$1.log"
  stop
  exit 1
}

start() {
  local fault=${1:-} f
  if [ "$fault" != all ]; then
    for f in ${fault//,/ }; do
      case "$f" in leak|flood|throttle) ;; *) say "FAULT=$fault: leak, flood or throttle (or several, comma-separated), or all"; exit 2 ;; esac
    done
  fi
  has() { [[ ",$fault," == *",$1,"* ]]; }
  stop
  for port in "$AGENT_PORT" "$STREAM_PORT" "$PROMETHEUS_PORT" "$DETECT_PORT"; do
    if ! "$PY" -c 'import socket, sys; socket.create_server(("127.0.0.1", int(sys.argv[1]))).close()' "$port" 2>/dev/null; then
      say "port $port is in use by another program: the demo needs $AGENT_PORT, $STREAM_PORT, $PROMETHEUS_PORT and $DETECT_PORT"
      exit 1
    fi
  done
  mkdir -p "$STATE"

  ip netns add "$NS"
  ip link add "${LINK}0" type veth peer name "${LINK}1" netns "$NS"
  ip addr add 10.77.0.1/24 dev "${LINK}0"
  ip link set "${LINK}0" up
  ip -n "$NS" addr add 10.77.0.2/24 dev "${LINK}1"
  ip -n "$NS" link set "${LINK}1" up
  ip -n "$NS" link set lo up

  # The mixin's rules and alerts, with the demo's shorter waits (demo/mixin.yaml).
  "$PY" -c 'import sys, yaml
config = yaml.safe_load(open("deploy/mixin/config.yaml"))
config.update(yaml.safe_load(open("demo/mixin.yaml")))
yaml.safe_dump(config, open(sys.argv[1], "w"))' "$STATE/mixin.yaml"
  "$PY" -m deploy.mixin.build --rules-only --config "$STATE/mixin.yaml" --out "$STATE/mixin" >/dev/null

  spawn agent .venv/bin/drums agent --port "$AGENT_PORT" --stream-port "$STREAM_PORT" --pin-dir "$PINS" --graph ros2
  sed -e "s/AGENT_PORT/$AGENT_PORT/" -e "s/DETECT_PORT/$DETECT_PORT/" demo/prometheus.yml >"$STATE/prometheus.yml"
  spawn prometheus prometheus --config.file="$STATE/prometheus.yml" --storage.tsdb.path="$STATE/prometheus" \
    --web.listen-address="127.0.0.1:$PROMETHEUS_PORT"
  wait_for agent "http://127.0.0.1:$AGENT_PORT/readyz"
  # The robot's own entities only: the rest of this machine (its host totals, processes that run no
  # node, TCP connections such as Prometheus's scrapes) is left out, as the paper left the host out.
  spawn detect .venv/bin/drums detect --agent "http://127.0.0.1:$AGENT_PORT" --port "$DETECT_PORT" \
    --log "$STATE/detect.jsonl" --ignore host --ignore process --ignore connection

  local env=(env DRUMS_DEMO_FAULT="$fault" DRUMS_DEMO_FAULT_AFTER="$FAULT_AFTER")
  local throttle_after=$THROTTLE_AFTER throttle_for=infinity
  if [ "$fault" = all ]; then  # each node its own fault, in turn
    FAULT_AFTER=${DRUMS_DEMO_FAULT_AFTER:-150}
    env=(env DRUMS_DEMO_FAULT_FOR=20)
    throttle_after=$((FAULT_AFTER + 80)) throttle_for=30
  fi
  spawn camera ip netns exec "$NS" "${env[@]}" "$PY" demo/robot.py camera
  spawn controller "${env[@]}" "$PY" demo/robot.py controller
  if [ "$fault" = all ]; then
    spawn processor "${env[@]}" DRUMS_DEMO_FAULT=leak DRUMS_DEMO_FAULT_AFTER="$FAULT_AFTER" "$PY" demo/robot.py processor
    spawn logger "${env[@]}" DRUMS_DEMO_FAULT=flood DRUMS_DEMO_FAULT_AFTER=$((FAULT_AFTER + 40)) "$PY" demo/robot.py logger
  else
    spawn processor "${env[@]}" DRUMS_DEMO_FAULT="$(has leak && echo leak)" "$PY" demo/robot.py processor
    spawn logger "${env[@]}" DRUMS_DEMO_FAULT="$(has flood && echo flood)" "$PY" demo/robot.py logger
  fi
  if has throttle || [ "$fault" = all ]; then
    local qdisc="ip netns exec $NS tc qdisc"
    spawn throttle sh -c "sleep $throttle_after && $qdisc add dev ${LINK}1 root tbf rate 4mbit burst 32kbit latency 400ms \
      && echo fault throttle started at \$(date +%s.%N) && sleep $throttle_for && $qdisc del dev ${LINK}1 root \
      && echo fault throttle ended at \$(date +%s.%N) && sleep infinity"
  fi
  wait_for prometheus "http://127.0.0.1:$PROMETHEUS_PORT/-/ready"

  local after=$FAULT_AFTER
  [ "$fault" = throttle ] && after=$THROTTLE_AFTER
  say "running${fault:+, with the fault $fault from $after s on}: the agent's live graph at http://127.0.0.1:$AGENT_PORT/,"
  say "Prometheus and its alerts at http://127.0.0.1:$PROMETHEUS_PORT/alerts, the detector's findings at"
  say "http://127.0.0.1:$DETECT_PORT/anomalies and in $STATE/detect.jsonl; make demo-stop ends it all"
  if [ -t 0 ] && [ -t 1 ]; then
    .venv/bin/drums top --agent "http://127.0.0.1:$AGENT_PORT" || true
    say "the demo goes on: make demo-stop ends it"
  fi
}

case "${1:-}" in
  start) start "${2:-}" ;;
  stop) stop ;;
  *) echo "usage: demo/demo.sh start [leak|flood|throttle|all] | stop" >&2; exit 2 ;;
esac
