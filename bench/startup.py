"""Time from launching `drums agent` to its first /metrics answer with the sockets probe attached:
cold (nothing pinned, so every BPF probe is compiled) and warm (programs left pinned by
--keep-loaded, so the agent only opens the pins). Goals: 2.5 s cold, 0.2 s warm.

    .venv/bin/python bench/startup.py [--runs 3]
"""
from __future__ import annotations

import argparse

from common import READY_LINE, Agent, drums_unload, fmt, main_wrapper, median, print_table, progress, require_root

GOALS = {"cold": 2.5, "warm": 0.2}


def one_start(keep_loaded: bool) -> tuple[float, float]:
    """(seconds to ready seen from outside, the agent's own figure for starting its probes)."""
    agent = Agent(keep_loaded=keep_loaded).start()
    try:
        seen = agent.wait_ready()
        return seen, agent.reported_startup()
    finally:
        agent.stop()


def run(args) -> None:
    require_root()
    results = {"cold": [], "warm": []}
    try:
        for i in range(args.runs):
            progress(f"cold start {i + 1}/{args.runs}")
            drums_unload()
            results["cold"].append(one_start(keep_loaded=False))
        progress("priming the pins for warm starts")
        drums_unload()
        one_start(keep_loaded=True)
        for i in range(args.runs):
            progress(f"warm start {i + 1}/{args.runs}")
            results["warm"].append(one_start(keep_loaded=True))
    finally:
        drums_unload()

    rows = []
    for kind, runs in results.items():
        seen = median(s for s, _ in runs)
        own = median(o for _, o in runs)
        rows.append([kind, fmt(seen), fmt(own), fmt(GOALS[kind], 1), f"{seen / GOALS[kind]:.2f}x"])
    print_table("Agent start-up: launch to first /metrics with probes attached",
                ["start", "median s to first metrics", "agent's own probe start s", "goal s", "measured / goal"],
                rows,
                [f"median of {args.runs} runs; 'to first metrics' runs from launching the process (Python "
                 f"imports included) until /metrics shows {READY_LINE}, polled every 10 ms",
                 "per run (s): " + "; ".join(f"{kind} " + ", ".join(fmt(seen) for seen, _ in runs)
                                             for kind, runs in results.items()),
                 "pins are removed at the end (drums unload)"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=3, help="starts of each kind (default 3)")
    args = parser.parse_args()
    main_wrapper(lambda: run(args))


if __name__ == "__main__":
    main()
