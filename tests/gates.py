"""FIFO gates: an input file replaced by a named pipe, so a test acts at a known point of a run.

A run that reaches the gated file blocks in open()/read() until the test writes the real bytes; the
test thereby knows the run is mid-way (on any machine, at any load) and can signal or kill it there.
The pattern of the labels SIGTERM test (tests/test_labels.py), shared by the build tests.
"""

from __future__ import annotations

import json
import os
import shutil
import threading
import time
from collections.abc import Callable
from pathlib import Path

from replicated_tree import _tok


class Gate:
    """A FIFO at `path` standing for a file whose content is `data`."""

    def __init__(self, path: Path, data: bytes) -> None:
        self.path, self.data = path, data
        os.mkfifo(path)

    def wait_reader(self, timeout: float = 300) -> int:
        """A write end, once a reader has the FIFO open (ENXIO until then; `readers()` then lists it);
        fail after `timeout` (a hang guard)."""
        t_end = time.monotonic() + timeout
        while True:
            try:
                fd = os.open(self.path, os.O_WRONLY | os.O_NONBLOCK)
                break
            except OSError:
                if time.monotonic() > t_end:
                    raise AssertionError(f"no process ever read {self.path}") from None
                time.sleep(0.01)
        while not self.readers():  # a reader still inside open() holds no descriptor yet
            if time.monotonic() > t_end:
                os.close(fd)
                raise AssertionError(f"the reader of {self.path} went away")
            time.sleep(0.01)
        return fd

    def readers(self) -> list[int]:
        """PIDs that hold the FIFO open for reading (this process too: an in-process run; never a write end)."""
        target, out = str(self.path), []
        for entry in os.listdir("/proc"):
            if not entry.isdigit():
                continue
            try:
                fds = os.listdir(f"/proc/{entry}/fd")
            except OSError:
                continue
            for fd in fds:
                try:
                    if os.readlink(f"/proc/{entry}/fd/{fd}") != target:
                        continue
                    flags = Path(f"/proc/{entry}/fdinfo/{fd}").read_text().split("flags:")[1].split()[0]
                except (OSError, IndexError):
                    continue
                if int(flags, 8) & 3 != os.O_WRONLY:
                    out.append(int(entry))
                    break
        return out

    def release(self, fd: int, timeout: float = 120) -> None:
        """Give the reader the real bytes and EOF (a reader that died meanwhile is fine); return once no
        process holds the FIFO open, so that a next write end meets a new reader, never this one."""
        try:
            os.set_blocking(fd, True)
            os.write(fd, self.data)
        except BrokenPipeError:
            pass
        finally:
            os.close(fd)
        t_end = time.monotonic() + timeout
        while self.readers():
            if time.monotonic() > t_end:
                raise AssertionError(f"{self.readers()} still hold {self.path} open")
            time.sleep(0.01)

    def serve(self, until: Callable[[], bool]) -> threading.Thread:
        """From now on, give every reader the real bytes, until `until()` (a run stopping after a signal
        may still read the file, e.g. a task retried elsewhere)."""
        def loop() -> None:
            while not until():
                try:
                    fd = os.open(self.path, os.O_WRONLY | os.O_NONBLOCK)
                except OSError:
                    time.sleep(0.01)
                    continue
                self.release(fd)

        t = threading.Thread(target=loop, daemon=True)
        t.start()
        return t


def gated_tree(tree: Path, dst: Path, scene: int, sample: int) -> tuple[Path, Gate]:
    """A copy of a `make_replicated_tree` tree (sensor files still linked) in which one camera image of
    `sample` of `scene` is a FIFO gate. The build reads it only while converting that sample's block."""
    shutil.copytree(tree, dst, symlinks=True)
    table = dst / "v1.0-mini" / "sample_data.json"
    rows = json.loads(table.read_text())
    token = _tok(f"replay-{scene:04d}", sample)
    row = next(r for r in rows if r["sample_token"] == token and r["filename"].endswith(".jpg"))
    data = (dst / row["filename"]).read_bytes()
    row["filename"] = "samples/gate.jpg"
    table.write_text(json.dumps(rows))
    return dst, Gate(dst / "samples" / "gate.jpg", data)
