"""Console throughput through the simulator's serial port: a host that
sends each line as soon as the previous one's `ok` is back (as OctoPrint
and Pronterface do), reading the port in blocks (pyserial's readline
reads a byte per system call, which would measure pyserial).

    lines_per_second.py [--lines N] [--speed F]

Measures `M105` (answered at once) and short `G1` moves (planned and
stepped: 0.05 mm at 100 mm/s, 0.5 ms each, back and forth every 200).
Prints lines per second for each; fails if a line is not answered with
an `ok` or the printer reports an error.
"""

import argparse
import os
import select
import time

import common
from common import Failure

# Longest wait for a reply, s.
REPLY_TIMEOUT = 30


class Port:
    """The simulator's port, read in blocks."""

    def __init__(self, path):
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
        self.pending = b""

    def close(self):
        os.close(self.fd)

    def readline(self):
        while b"\n" not in self.pending:
            ready, _, _ = select.select([self.fd], [], [], REPLY_TIMEOUT)
            if not ready:
                return None
            self.pending += os.read(self.fd, 4096)
        line, self.pending = self.pending.split(b"\n", 1)
        return line.decode().strip()


def exchange(port, line):
    """Sends `line` and reads up to its `ok`; returns the reply lines."""
    os.write(port.fd, line.encode() + b"\n")
    replies = []
    while True:
        reply = port.readline()
        if reply is None:
            raise Failure(f"no ok for {line!r} within {REPLY_TIMEOUT} s; got {replies}")
        replies.append(reply)
        if reply == "ok":
            return replies


def rate(port, lines):
    """Streams `lines`; returns lines per second."""
    start = time.perf_counter()
    for line in lines:
        replies = exchange(port, line)
        errors = [r for r in replies if r.startswith("!!")]
        if errors:
            raise Failure(f"{line!r}: {errors}")
    return len(lines) / (time.perf_counter() - start)


def harness():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lines", type=int, default=5000)
    parser.add_argument("--speed", type=float, default=1.0)
    parser.add_argument("--keep", action="store_true", help="keep the work folder (logs) and name it")
    args = parser.parse_args()
    with common.workdir("onechip-lines-", args.keep) as work:
        sd = common.make_sd(work, {})
        with common.Simulator(work, sd, args.speed) as sim:
            port = Port(str(sim.link))
            exchange(port, "SET_KINEMATIC_POSITION X=100 Y=100 Z=10")
            exchange(port, "G91")
            m105 = rate(port, ["M105"] * args.lines)
            # Back and forth along X, 0.05 mm at a time.
            moves = [f"G1 X{0.05 if (i // 200) % 2 == 0 else -0.05} F6000" for i in range(args.lines)]
            g1 = rate(port, moves)
            exchange(port, "M400")
            port.close()
            served = sim.finish()
        if served["errors"] or served["shutdown"]:
            raise Failure(f"errors {served['errors'][:5]}, shutdown {served['shutdown']}")
        print(f"M105: {m105:.0f} lines/s; G1 (0.05 mm moves, {args.speed}x): {g1:.0f} lines/s")


if __name__ == "__main__":
    common.main(harness)
