"""A misbehaving graph reader for the tests: one good graph, one line of garbage, then silence."""
import json
import sys
import time

if __name__ == "__main__":
    print(json.dumps({"state": {"nodes": [{"name": "/only"}]}}), flush=True)
    time.sleep(0.5)
    print("{not json", flush=True)
    time.sleep(60)
    sys.exit(0)
