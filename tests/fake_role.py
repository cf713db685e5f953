"""A fake rig role for the launcher tests (stands in for ``ilcrig host|plant|drive``).

``python tests/fake_role.py ROLE [--sleep S] [--exit N] [--crash] [--ignore-term] [role args…]``

* writes ``$FAKE_ROLE_DIR/<role>[<node>].<pid>`` containing its argv (one per line) at start,
  when that variable is set, so a test knows its pid and what the launcher passed;
* sleeps ``S`` seconds (default: forever), then exits with ``N`` (default 0), or raises
  (``--crash``: a traceback on stderr, exit code 1);
* ``--ignore-term`` ignores SIGTERM (the launcher must escalate to SIGKILL);
* ``--wait-drives N`` (a host): first waits (≤ 30 s) until N clients are on the hub's
  ``fieldbus`` and ``io`` buses (given with ``--hub``) and the fieldbus carried a frame per
  client (boot-up/heartbeats), and writes ``fieldbus_clients io_clients fieldbus_frames`` to
  ``$FAKE_ROLE_DIR/hub_stats``.

Unknown arguments (the role's real options: ``--bus``, ``--hub``, ``--out`` …) are accepted.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time


def wait_drives(hub: str, n: int, piddir: str | None) -> None:
    from bus.transports.hub.stats import query_hub_stats

    deadline = time.monotonic() + 30
    while True:
        stats = query_hub_stats(hub)
        fb, io = stats.get("fieldbus"), stats.get("io")
        if fb and io and fb.clients >= n and io.clients >= n and fb.frames >= n:
            break
        if time.monotonic() > deadline:
            raise TimeoutError(f"drives not on the hub: {stats}")
        time.sleep(0.05)
    if piddir:
        with open(os.path.join(piddir, "hub_stats"), "w") as fh:
            fh.write(f"{fb.clients} {io.clients} {fb.frames}\n")


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(allow_abbrev=False)
    p.add_argument("role")
    p.add_argument("--sleep", type=float, default=None)
    p.add_argument("--exit", type=int, default=0)
    p.add_argument("--crash", action="store_true")
    p.add_argument("--ignore-term", action="store_true")
    p.add_argument("--node", type=int, default=None)
    p.add_argument("--wait-drives", type=int, default=0)
    p.add_argument("--hub", default=None)
    args, _ = p.parse_known_args(argv)
    if args.ignore_term:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    name = f"{args.role}{args.node if args.node is not None else ''}"
    piddir = os.environ.get("FAKE_ROLE_DIR")
    if piddir:
        tmp = os.path.join(piddir, f".{name}.{os.getpid()}")
        with open(tmp, "w") as fh:
            fh.write("\n".join(argv) + "\n")
        os.replace(tmp, os.path.join(piddir, f"{name}.{os.getpid()}"))
    print(f"fake {name} pid {os.getpid()} started", flush=True)
    if args.wait_drives:
        wait_drives(args.hub, args.wait_drives, piddir)
    if args.sleep is None:
        while True:
            time.sleep(3600)
    time.sleep(args.sleep)
    if args.crash:
        raise RuntimeError(f"fake {name} crashed on purpose")
    return args.exit


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
