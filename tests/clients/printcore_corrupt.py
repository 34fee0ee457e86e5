"""Printrun's printcore (Pronterface's engine) streams a print through a
line that corrupts 1 % of the bytes going to the printer.

A proxy pseudo-terminal sits between printcore and the simulator's port
and flips bits in 1 % of the bytes host -> printer (seeded, so every run
corrupts the same bytes; line ends are left alone, as a byte turned into a
line end would split a line into pieces Marlin's protocol cannot tell from
real lines, and no bit position is flipped twice in one line, which its
XOR checksum cannot see). printcore numbers and checksums every line, so each
corrupted line must be refused and asked for again (`Resend: N`), never
run. The file moves relatively (G91, M83): a line run twice or lost moves
every later position, so the final positions must equal the batch run
of the clean file (step counts within 10 %: see common.compare_motion).
"""

import argparse
import os
import random
import select
import threading
import time
import tty
from pathlib import Path

from printrun import gcoder
from printrun.printcore import printcore

import common
from common import Failure, wait_for

# The print, 110 s of virtual time (heating, homing, 150 short moves),
# takes 11 s (see octoprint_print.py on the choice of speed).
DEFAULT_SPEED = 10.0
# Bytes in a hundred corrupted on the way to the printer.
CORRUPT_PERCENT = 1.0
SEED = 20240229


def relative_print(moves=150, seed=SEED):
    """Heat, home, then `moves` short relative moves with extrusion that
    wander around the bed centre, and report the position."""
    rng = random.Random(seed)
    lines = ["M104 S200", "G28", "G1 Z0.3 F600", "G1 X110 Y110 F9000", "M109 S200", "G91", "M83"]
    x = y = 110.0
    for _ in range(moves):
        dx, dy = (round(rng.uniform(-4, 4), 3) for _ in range(2))
        # Back towards the centre when far from it.
        dx, dy = (-dx if abs(p + d - 110) > 40 else d for p, d in ((x, dx), (y, dy)))
        x, y = x + dx, y + dy
        feed = rng.choice([1200, 1800, 3000, 6000])
        lines.append(f"G1 X{dx} Y{dy} E{round(rng.uniform(0.01, 0.2), 4)} F{feed}")
    lines += ["G90", "M82", "M104 S0", "M400", "M114"]
    return "\n".join(lines) + "\n"


class CorruptingLine:
    """A pty pair for printcore, forwarding to the simulator's port: bytes
    to the printer are corrupted at `percent` %, replies pass unchanged.
    It ends when printcore closes its side, closing the printer's."""

    def __init__(self, printer_port, percent, seed):
        self.master, slave = os.openpty()
        tty.setraw(slave)
        self.port = os.ttyname(slave)
        # printcore opens the slave by name; this handle keeps it usable
        # until then.
        self._slave = slave
        self.printer = os.open(printer_port, os.O_RDWR | os.O_NOCTTY)
        self.rng = random.Random(seed)
        self.percent = percent
        self.sent = 0
        self.corrupted = 0
        self.corrupted_lines = set()
        # Bits flipped so far in the line being sent.
        self.flipped_bits = set()
        self.lines_to_printer = 0
        self.replies = bytearray()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def release_own_handle(self):
        """Once printcore has the port open: from then on its close is
        the proxy's hang-up."""
        os.close(self._slave)

    def _corrupt(self, data):
        out = bytearray(data)
        for i, byte in enumerate(out):
            if byte == ord("\n"):
                self.lines_to_printer += 1
                self.flipped_bits = set()
                continue
            if self.rng.random() * 100 < self.percent:
                # A bit flipped twice in one line cancels out in the XOR
                # checksum of Marlin's protocol: no printer speaking it can
                # see that, so the line's other flips use other bits.
                bits = [b for b in range(7) if b not in self.flipped_bits]
                if not bits:
                    continue
                bit = self.rng.choice(bits)
                self.flipped_bits.add(bit)
                mask = 1 << bit
                bad = byte ^ mask
                if bad in (ord("\n"), ord("\r")):
                    bad = byte ^ 0x40
                out[i] = bad
                self.corrupted += 1
                self.corrupted_lines.add(self.lines_to_printer)
        self.sent += len(out)
        return bytes(out)

    def _run(self):
        try:
            while True:
                ready, _, _ = select.select([self.master, self.printer], [], [])
                if self.master in ready:
                    try:
                        data = os.read(self.master, 4096)
                    except OSError:
                        data = b""
                    if not data:
                        return
                    os.write(self.printer, self._corrupt(data))
                if self.printer in ready:
                    data = os.read(self.printer, 4096)
                    self.replies += data
                    os.write(self.master, data)
        finally:
            os.close(self.printer)


def harness():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--speed", type=float, default=DEFAULT_SPEED)
    parser.add_argument(
        "--percent", type=float, default=CORRUPT_PERCENT, help="bytes corrupted in a hundred (0: a clean line)"
    )
    parser.add_argument("--keep", action="store_true", help="keep the work folder (logs) and name it")
    args = parser.parse_args()
    gcode = relative_print()
    with common.workdir("onechip-printcore-", args.keep) as work:
        sd = common.make_sd(work, {})
        job = Path(work) / "relative.gcode"
        job.write_text(gcode)
        with common.Simulator(work, sd, args.speed) as sim:
            line = CorruptingLine(str(sim.link), args.percent, SEED)
            try:
                stream(line, gcode)
            except Failure as e:
                sim.stop()
                raise Failure(
                    f"{e}\n--- replies (tail) ---\n{line.replies.decode(errors='replace')[-3000:]}"
                    f"\n--- simulator ---\n{sim.output()}"
                )
            finally:
                (Path(work) / "replies.txt").write_bytes(bytes(line.replies))
            served = sim.finish()
        replies = line.replies.decode(errors="replace").splitlines()
        resends = [r for r in replies if r.lower().startswith(("resend", "rs "))]
        print(
            f"{line.corrupted} of {line.sent} bytes corrupted, in {len(line.corrupted_lines)} lines; "
            f"{len(resends)} resend requests"
        )
        if args.percent > 0 and line.corrupted == 0:
            raise Failure("nothing was corrupted: the test would prove nothing")
        if len(resends) < len(line.corrupted_lines):
            raise Failure(
                f"{len(line.corrupted_lines)} lines arrived corrupted but the printer asked for only "
                f"{len(resends)} again: corrupted lines ran. Replies:\n" + "\n".join(replies[-60:])
            )
        if served["errors"]:
            raise Failure(f"the printer reported errors: {served['errors'][:10]}")
        # printcore streams line by line in real time: positions exact,
        # step counts within 10 % (see compare_motion).
        common.compare_motion(
            served, common.batch_summary(work, sd, job), "printcore over a corrupting line", 0.10
        )


def stream(line, gcode):
    """Connects printcore through `line`, prints `gcode`, disconnects."""
    core = printcore(line.port, 115200)
    wait_for("printcore to connect", lambda: core.online, 30)
    line.release_own_handle()
    start = time.monotonic()
    if not core.startprint(gcoder.LightGCode(gcode.splitlines())):
        raise Failure("printcore would not start the print")
    try:
        wait_for("the print to end", lambda: not core.printing and core.print_thread is None, 180, every=0.1)
    finally:
        core.disconnect()
    print(f"printcore streamed {len(gcode.splitlines())} lines in {time.monotonic() - start:.1f} s")
    line.thread.join(10)


if __name__ == "__main__":
    common.main(harness)
