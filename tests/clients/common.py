"""Shared parts of the client harnesses: the simulator serving its console
on a pseudo-terminal, its batch run of the same file, and the comparison
of their JSON summaries.

The simulator binary is $ONECHIP_SIM, or target/release/onechip-sim of
this checkout.
"""

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SHIPPED = REPO / "sdcard-configs" / "octopus-pro-h723"
# The shipped sample print: heats, homes, prints a 40 mm square.
SAMPLE_GCODE = SHIPPED / "first-layer-square.gcode"


class Failure(Exception):
    """The client did not get what a printer owner would expect."""


def simulator_binary():
    path = Path(os.environ.get("ONECHIP_SIM") or REPO / "target/release/onechip-sim")
    if not path.is_file():
        raise Failure(
            f"no simulator at {path}: build it with "
            "`cargo build -p onechip-host --release` or set ONECHIP_SIM"
        )
    return path


def make_sd(root, files):
    """An SD folder under `root` with the shipped printer.cfg and `files`
    (name -> text)."""
    sd = Path(root) / "sd"
    sd.mkdir(parents=True)
    shutil.copy(SHIPPED / "printer.cfg", sd / "printer.cfg")
    for name, text in files.items():
        (sd / name).write_text(text)
    return sd


@contextlib.contextmanager
def workdir(prefix, keep):
    """A temporary folder, kept (and named) if `keep`."""
    if keep:
        path = tempfile.mkdtemp(prefix=prefix)
        print(f"work folder: {path}")
        yield path
    else:
        with tempfile.TemporaryDirectory(prefix=prefix) as path:
            yield path


def wait_for(what, check, timeout, every=0.05):
    """Polls `check` until it returns a true value, which is returned;
    fails after `timeout` s naming `what`."""
    deadline = time.monotonic() + timeout
    while True:
        value = check()
        if value:
            return value
        if time.monotonic() > deadline:
            raise Failure(f"timed out after {timeout} s waiting for {what}")
        time.sleep(every)


class Simulator:
    """`onechip-sim SD --serial LINK --speed F --summary-json JSON`, as a
    context manager that kills it if the harness fails first."""

    def __init__(self, workdir, sd, speed, name="printer"):
        workdir = Path(workdir)
        self.link = workdir / f"{name}.tty"
        self.summary_path = workdir / f"{name}.json"
        self.log_path = workdir / f"{name}.log"
        self.log = open(self.log_path, "w")
        command = [
            str(simulator_binary()),
            str(sd),
            "--serial",
            str(self.link),
            "--speed",
            str(speed),
            "--summary-json",
            str(self.summary_path),
        ]
        self.proc = subprocess.Popen(command, stdout=self.log, stderr=subprocess.STDOUT)
        wait_for(
            f"the simulator's port {self.link}",
            lambda: self.link.exists() or self._exited(),
            10,
        )
        if self.proc.poll() is not None:
            raise Failure(f"the simulator exited at once:\n{self.output()}")

    def _exited(self):
        return self.proc.poll() is not None

    def output(self):
        self.log.flush()
        return self.log_path.read_text()

    def finish(self, timeout=60):
        """Waits for the simulator to end (its host closed the port) and
        returns its JSON summary."""
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            raise Failure(
                f"the simulator did not end within {timeout} s of the host "
                f"closing the port:\n{self.output()}"
            )
        if not self.summary_path.exists():
            raise Failure(f"the simulator wrote no summary:\n{self.output()}")
        return json.loads(self.summary_path.read_text())

    def __enter__(self):
        return self

    def stop(self):
        """Ends the simulator as Ctrl-C would (it still sums up)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def __exit__(self, *exc):
        self.stop()
        self.log.close()
        return False


def batch_summary(workdir, sd, gcode):
    """The JSON summary of `onechip-sim SD GCODE` (the file read from the
    SD folder, no host)."""
    out = Path(workdir) / f"batch-{Path(gcode).stem}.json"
    run = subprocess.run(
        [str(simulator_binary()), str(sd), str(gcode), "--summary-json", str(out)],
        capture_output=True,
        text=True,
    )
    if not out.exists():
        raise Failure(f"the batch run wrote no summary:\n{run.stdout}{run.stderr}")
    return json.loads(out.read_text())


def compare_motion(served, batch, what, count_tolerance=0.0):
    """Fails unless `served` (a print through a host) moved every stepper
    as `batch` did: the same final positions and final G-code position,
    and the same step counts, or within `count_tolerance` (a fraction) of
    them. A host that streams line by line in real time lets Klipper's
    timers decide when moves are planned (released 0.1 s after the first
    one queued, flushed when the buffer runs low), so its moves may stop
    where the batch run's flowed on: the path and where every stepper
    ends are the same, but pressure advance and input shaping make their
    few extra steps back and forth at different stops."""
    problems = []
    if [s["name"] for s in served["steppers"]] != [s["name"] for s in batch["steppers"]]:
        problems.append("different steppers")
    for s, b in zip(served["steppers"], batch["steppers"]):
        if s["position"] != b["position"]:
            problems.append(f"{s['name']} position: {s['position']} through {what}, {b['position']} in the batch run")
        if abs(s["steps"] - b["steps"]) > count_tolerance * b["steps"]:
            problems.append(f"{s['name']} steps: {s['steps']} through {what}, {b['steps']} in the batch run")
    for axis, s, b in zip("XYZE", served["final_position"], batch["final_position"]):
        if abs(s - b) > 1e-9:
            problems.append(f"final {axis}: {s} through {what}, {b} in the batch run")
    if served["shutdown"]:
        problems.append(f"the simulator shut down: {served['shutdown']}")
    if problems:
        raise Failure("motion differs from the batch run:\n  " + "\n  ".join(problems))
    steps = ", ".join(
        f"{s['name']} {s['steps']} ({b['steps']})" for s, b in zip(served["steppers"], batch["steppers"])
    )
    print(f"same motion as the batch run: steps (batch run's) {steps}, same final positions")


def main(harness):
    """Runs `harness()`, printing PASS or FAIL and exiting 0 or 1."""
    start = time.monotonic()
    name = Path(sys.argv[0]).stem
    try:
        harness()
    except Failure as e:
        print(f"FAIL {name} ({time.monotonic() - start:.1f} s): {e}", flush=True)
        sys.exit(1)
    print(f"PASS {name} ({time.monotonic() - start:.1f} s)", flush=True)
