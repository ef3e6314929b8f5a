"""Issue 12 item 14: loader worker start method and scripts without a `__main__` guard.

The first test shows the fork hazard's mechanism: a forked child that uses the parent's zarr IO
loop waits forever (zarr >= 3.0.3 resets the loop in the child). The others: a script without
`if __name__ == "__main__":` gets one clear line where the start method re-imports it (the
forkserver default, or spawn), and a guarded script works.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def bad_store(synth_store: Path, tmp_path: Path) -> Path:
    out = tmp_path / "bad.zarr"
    shutil.copytree(synth_store, out)
    (shard,) = [p for p in (out / "labels/semantics/c").rglob("*") if p.is_file()]
    shard.write_bytes(shard.read_bytes()[:100])  # any read of it fails (shard index checksum)
    return out


def _run(code: str, tmp_path: Path, name: str = "script.py", timeout: int = 240) -> subprocess.CompletedProcess:
    script = tmp_path / name
    script.write_text(textwrap.dedent(code))
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=timeout)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_mechanism_child_using_parents_zarr_loop_hangs(synth_store: Path, bad_store: Path, tmp_path: Path) -> None:
    r = _run(f"""
        import os, signal, zarr, zarr.core.sync as zs
        g = zarr.open_group({str(bad_store)!r}, mode="r")
        try:
            g["labels/semantics"][0]
        except Exception:
            pass
        parent_loop = zs.loop[0]
        for undo in (False, True):
            pid = os.fork()
            if pid == 0:
                if undo:
                    zs.loop[0] = parent_loop  # a zarr without its after-fork reset
                signal.alarm(3)
                zarr.open_group({str(synth_store)!r}, mode="r")["labels/semantics"][1]
                os._exit(0)
            _, status = os.waitpid(pid, 0)
            print("undo" if undo else "reset", "hung" if os.WIFSIGNALED(status) else "ok")
    """, tmp_path)
    assert r.stdout.split("\n")[:2] == ["reset ok", "undo hung"], r.stdout + r.stderr


SCRIPT = """
    from fastocc.data import ImageAugConfig, LoaderConfig, SampleConfig, make_loader
    cfg = SampleConfig(image=ImageAugConfig(height=96, width=160))
    {body}
"""
LOOP = """loader = make_loader(LoaderConfig(store={store!r}, batch_size=2, sample=cfg), num_workers=2{ctx})
    print("samples", sum(len(b.sample_index) for b in loader))"""


@pytest.mark.timeout(120)
@pytest.mark.parametrize("ctx", ["", ', multiprocessing_context="spawn"'])
def test_unguarded_script_gets_one_clear_line(synth_store: Path, tmp_path: Path, ctx: str) -> None:
    """Was: 'DataLoader worker (pid(s) ...) exited unexpectedly' after the workers re-ran the script."""
    r = _run(SCRIPT.format(body=LOOP.format(store=str(synth_store), ctx=ctx)), tmp_path)
    assert r.returncode == 1
    last = r.stderr.strip().splitlines()[-1]
    assert "script.py:4 creates a data loader with workers at module level" in last, r.stderr
    assert "if __name__ == \"__main__\":" in last and ("'spawn'" in last or "'forkserver'" in last)
    assert "exited unexpectedly" not in r.stderr


@pytest.mark.parametrize("edited", [False, True])
def test_guard_check_reads_the_script_as_it_ran(tmp_path: Path, edited: bool) -> None:
    """A guarded script edited on disk while it runs (lines added on top) must not be mistaken for module-level
    loader code; an unguarded call is still caught."""
    edit = "open(__file__, 'w').write(chr(10) * 40 + open(__file__).read())" if edited else "pass"
    r = _run(f"""
        from fastocc.data.workers import check_main_guard
        check_main_guard("spawn") if {not edited} else None

        def main():
            {edit}
            check_main_guard("spawn")
            print("ok")

        if __name__ == "__main__":
            main()
    """, tmp_path)
    if edited:
        assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr
    else:
        assert r.returncode == 1 and "script.py:3 creates a data loader" in r.stderr, r.stderr


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_guarded_script_works(synth_store: Path, tmp_path: Path) -> None:
    body = "def main():\n        " + LOOP.format(store=str(synth_store), ctx="") \
        .replace("\n    ", "\n        ") + "\n    if __name__ == \"__main__\":\n        main()"
    r = _run(SCRIPT.format(body=body), tmp_path)
    assert r.returncode == 0 and "samples 6" in r.stdout, r.stderr[-2000:]


def test_forkserver_workers_ignore_sigint_and_the_parent_does_not(tmp_path: Path) -> None:
    """A terminal's Ctrl-C reaches the whole process group; a worker hit while starting printed a traceback."""
    r = _run("""
        import signal
        from fastocc.data.workers import default_worker_context

        def handler(q):
            q.put(signal.getsignal(signal.SIGINT) == signal.SIG_IGN)

        if __name__ == "__main__":
            import fastocc._worker_signals  # imported outside the forkserver: no effect
            ctx = default_worker_context()
            q = ctx.Queue()
            p = ctx.Process(target=handler, args=(q,))
            p.start()
            print("worker", q.get(timeout=120))
            p.join()
            print("parent", signal.getsignal(signal.SIGINT) == signal.SIG_IGN)
    """, tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines() == ["worker True", "parent False"]


def test_a_sigterm_while_the_loader_starts_is_raised_after_it_started() -> None:
    """SIGTERM (the CLI's handler raises SystemExit) arriving inside `iter(loader)` is held until the
    iterator exists: torch's half-built iterator printed "no attribute '_workers_status'" on cleanup."""
    import os
    import signal

    from fastocc.data.workers import start_iteration

    events: list[str] = []

    class Loader:
        def __iter__(self):  # noqa: ANN204 - a loader whose start gets a SIGTERM half-way
            os.kill(os.getpid(), signal.SIGTERM)
            events.append("started")
            return iter([1, 2])

    def handler(signum: int, frame: object) -> None:
        events.append("handler")
        raise SystemExit(143)

    old = signal.signal(signal.SIGTERM, handler)
    try:
        with pytest.raises(SystemExit):
            start_iteration(Loader())
        assert events == ["started", "handler"]
        assert signal.getsignal(signal.SIGTERM) is handler  # the caller's handler is back
    finally:
        signal.signal(signal.SIGTERM, old)


def test_loader_workers_outlive_a_sigterm_to_the_job(synth_store: Path, tmp_path: Path) -> None:
    """A scheduler's SIGTERM reaches every process of the job; the trainer stops at a step boundary and
    needs its workers until then. torch's worker loop installs its own SIGTERM handler (it dies unless
    the sender is its parent, here the forkserver), which undid the forkserver's ignore: a batch not yet
    made when the signal came failed with "DataLoader worker exited unexpectedly" (seen in CI)."""
    body = f"""
    import os, signal, sys, time
    sys.path.insert(0, {str(REPO / "tests")!r})
    from proc_tools import alive, descendants, loader_processes

    def main():
        loader = make_loader(LoaderConfig(store={str(synth_store)!r}, batch_size=1, sample=cfg), num_workers=1)
        it = iter(loader)
        n = len(next(it).sample_index)
        workers = [w for server in loader_processes(os.getpid()) for w in descendants(server)]
        for w in workers:
            os.kill(w, signal.SIGTERM)  # from the job, not the worker's parent
        time.sleep(1.0)
        print("alive", sum(alive(w) for w in workers), "of", len(workers))
        print("samples", n + sum(len(b.sample_index) for b in it))

    if __name__ == "__main__":
        main()
    """
    r = _run(SCRIPT.format(body=body), tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.splitlines() == ["alive 1 of 1", "samples 6"], r.stdout + r.stderr[-3000:]
