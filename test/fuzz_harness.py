"""Fuzzing every reader of untrusted input: mutated files through a decoder in a guarded worker process.

The rule each decoder must keep (issue "bad input never crashes, hangs, escapes or
silently corrupts"): on any input it either returns, or raises the project's own
error (a :class:`~t42_transfer.data.errors.DataFileError`, or ``ValueError`` where a
decoder documents it) whose message is one line naming the file.  Anything else is an
*escape*:

- ``crash``: the worker died from a signal (a segfault in a C extension);
- ``hang``: the call ran past ``timeout_s`` (the worker is interrupted by SIGALRM);
- ``memory``: the call allocated more than ``mem_mb`` beyond what the worker held
  before it (an address-space limit turns that into MemoryError);
- ``exception``: any other exception type, or a message that is not one line
  naming the file;
- ``wrote``: a file appeared outside the case's own directory (the worker runs in
  an empty scratch directory that is checked after every case).

:class:`DecoderWorker` keeps one worker process per decoder (imports are paid once)
and restarts it after a crash.  :func:`mutated` is a hypothesis strategy: a valid
seed file's bytes with a drawn list of mutations (bit flips, byte overwrites with
interesting values, insertions, deletions, duplicated chunks, truncation), so
failures shrink to few mutations.  Typical use::

    worker = DecoderWorker("t42_transfer.models.checkpoint:load_model")
    @given(mutated(seed_bytes))
    def test_checkpoints_are_total(data):
        worker.check_bytes(data, "model.safetensors")
"""

from __future__ import annotations

import json
import os
import select
import shutil
import subprocess
import sys
import tempfile
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

REPO = Path(__file__).resolve().parents[1]
PARENT_GRACE_S = 10.0
"""How much longer than the worker's own alarm the parent waits before it kills the worker."""
INTERESTING = (b"\x00", b"\xff", b"\x7f", b"\x80", b"\xff\xff\xff\x7f", b"\x00\x00\x00\x80",
               b"\xff\xff\xff\xff\xff\xff\xff\x7f", b"nan", b"-1", b"1e309", b"[", b"{", b"'", b"\n")


@dataclass(frozen=True)
class Verdict:
    outcome: str
    """``accepted`` or ``refused`` (both keep the rule); an escape raises instead."""
    detail: str = ""


class Escape(AssertionError):
    """A decoder broke the rule on one input; the message says how and where the input is kept."""


class DecoderWorker:
    """A worker process that runs ``target(path)`` on case files, one at a time, under guards."""

    def __init__(self, target: str, errors: str = "t42_transfer.data.errors:DataFileError", mem_mb: int = 512,
                 timeout_s: float = 10.0, keep_dir: Path | None = None, grace_s: float = PARENT_GRACE_S) -> None:
        """``grace_s``: how much longer than ``timeout_s`` the parent waits before it kills the worker."""
        self.target, self.errors, self.mem_mb, self.timeout_s = target, errors, mem_mb, timeout_s
        self.grace_s = grace_s
        self.root = Path(tempfile.mkdtemp(prefix="t42-fuzz-"))
        self.keep_dir = keep_dir
        self.counts = {"accepted": 0, "refused": 0}
        self._proc: subprocess.Popen[str] | None = None
        self._case = 0

    # ------------------------------------------------------------------ process
    def _start(self) -> subprocess.Popen[str]:
        if self._proc is None or self._proc.poll() is not None:
            scratch = self.root / "scratch"
            scratch.mkdir(exist_ok=True)
            env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), str(REPO / "test")]), OMP_NUM_THREADS="1",
                       MKL_NUM_THREADS="1")
            self._proc = subprocess.Popen(
                [sys.executable, "-u", str(Path(__file__)), self.target, self.errors, str(self.mem_mb),
                 str(self.timeout_s)],
                cwd=scratch, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
            ready = self._proc.stdout.readline()
            if ready.strip() != "ready":
                raise RuntimeError(f"fuzz worker for {self.target} did not start: {ready!r}")
        return self._proc

    def close(self) -> None:
        if self._proc is not None:
            self._proc.stdin.close()
            try:
                self._proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
            self._proc.stdout.close()
        shutil.rmtree(self.root, ignore_errors=True)

    def __enter__(self) -> DecoderWorker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ cases
    def new_case_dir(self) -> Path:
        """An empty directory for the next case's files (a bag is a directory)."""
        self._case += 1
        case = self.root / f"case_{self._case:06d}"
        case.mkdir()
        return case

    def check_bytes(self, data: bytes, name: str) -> Verdict:
        """Decode a file called ``name`` holding ``data``."""
        path = self.new_case_dir() / name
        path.write_bytes(data)
        return self.check_path(path)

    def check_path(self, path: Path) -> Verdict:
        """Decode ``path`` (inside a :meth:`new_case_dir`); the verdict, or :class:`Escape`."""
        proc = self._start()
        case_dir = path.parent if path.parent.name.startswith("case_") else path
        before = _listing(self.root / "scratch")
        proc.stdin.write(str(path) + "\n")
        proc.stdin.flush()
        # the worker's own alarm cannot interrupt C code that never checks for signals: a parent-side limit too
        ready, _, _ = select.select([proc.stdout], [], [], self.timeout_s + self.grace_s)
        if not ready:
            proc.kill()
            proc.wait()
            self._proc = None
            proc.stdin.close()
            proc.stdout.close()
            raise self._escape(case_dir, "hang", f"no answer within {self.timeout_s + self.grace_s} s (killed)")
        line = proc.stdout.readline()
        if not line:  # the worker died on this case
            code = proc.wait()
            self._proc = None
            proc.stdin.close()
            proc.stdout.close()
            raise self._escape(case_dir, "crash", f"worker exited with {code} (signal {-code})" if code < 0
                               else f"worker exited with {code}")
        result = json.loads(line)
        after = _listing(self.root / "scratch")
        if after != before:
            raise self._escape(case_dir, "wrote", f"new files outside the case: {sorted(after - before)[:5]}")
        if result["outcome"] not in self.counts:
            raise self._escape(case_dir, result["outcome"], result["detail"])
        self.counts[result["outcome"]] += 1
        shutil.rmtree(case_dir, ignore_errors=True)
        return Verdict(result["outcome"], result["detail"])

    def _escape(self, case_dir: Path, kind: str, detail: str) -> Escape:
        kept = case_dir
        if self.keep_dir is not None:
            self.keep_dir.mkdir(parents=True, exist_ok=True)
            kept = self.keep_dir / f"{kind}_{case_dir.name}"
            # regular files only: a case may hold a FIFO, which copying would block on or refuse
            shutil.copytree(case_dir, kept, dirs_exist_ok=True,
                            ignore=lambda d, names: [n for n in names if not (Path(d, n).is_file()
                                                                             or Path(d, n).is_dir())])
        return Escape(f"{self.target}: {kind}: {detail} (input kept at {kept})")


def _listing(directory: Path) -> set[str]:
    return {str(p.relative_to(directory)) for p in directory.rglob("*")} if directory.exists() else set()


# --------------------------------------------------------------------------- running
def fuzz(worker: DecoderWorker, strategy: st.SearchStrategy[bytes], name: str, examples: int,
         check: Callable[[bytes], object] | None = None) -> dict[str, int]:
    """``examples`` derandomized cases of ``strategy``, each decoded as a file called ``name``; the counts.

    ``check`` replaces that when a case is more than one file (a bag directory with one file mutated).
    An escape raises (hypothesis then shrinks it); the accepted/refused counts of this run are printed
    (``pytest -s``) and returned.
    """
    before = dict(worker.counts)

    @settings(max_examples=examples, deadline=None, derandomize=True, database=None,
              suppress_health_check=list(HealthCheck))
    @given(strategy)
    def run(data: bytes) -> None:
        if check is None:
            worker.check_bytes(data, name)
        else:
            check(data)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # hypothesis's notes on derandomize are not the subject here
        run()
    counts = {kind: worker.counts[kind] - before[kind] for kind in before}
    print(f"{worker.target} fuzz ({name}): {sum(counts.values())} cases, {counts['accepted']} accepted, "
          f"{counts['refused']} refused, 0 escapes")
    return counts


# --------------------------------------------------------------------------- mutations
@st.composite
def mutated(draw: st.DrawFn, seed: bytes, max_mutations: int = 8) -> bytes:
    """``seed`` with up to ``max_mutations`` drawn mutations (at least one)."""
    data = bytearray(seed)
    for _ in range(draw(st.integers(1, max_mutations))):
        op = draw(st.sampled_from(("flip", "overwrite", "insert", "delete", "duplicate", "truncate")))
        at = draw(st.integers(0, max(len(data) - 1, 0)))
        if op == "flip" and data:
            data[at] ^= 1 << draw(st.integers(0, 7))
        elif op == "overwrite":
            value = draw(st.sampled_from(INTERESTING) | st.binary(min_size=1, max_size=8))
            data[at:at + len(value)] = value
        elif op == "insert":
            data[at:at] = draw(st.sampled_from(INTERESTING) | st.binary(min_size=1, max_size=64))
        elif op == "delete":
            del data[at:at + draw(st.integers(1, 64))]
        elif op == "duplicate" and data:
            size = draw(st.integers(1, 256))
            chunk = data[at:at + size]
            data[at:at] = chunk * draw(st.integers(1, 4))
        elif op == "truncate":
            del data[at:]
    return bytes(data)


# --------------------------------------------------------------------------- the worker process
def _load(spec: str) -> object:
    import importlib

    module, _, name = spec.partition(":")
    return getattr(importlib.import_module(module), name)


def _worker(target_spec: str, errors_spec: str, mem_mb: int, timeout_s: float) -> None:
    import resource
    import signal

    target = _load(target_spec)
    errors = tuple(_load(s) for s in errors_spec.split(","))

    def on_alarm(signum: int, frame: object) -> None:
        raise _Hang(f"still running after {timeout_s} s")

    signal.signal(signal.SIGALRM, on_alarm)
    # the address space held now (interpreter, torch, numpy...) plus mem_mb for one decode
    with open("/proc/self/statm") as statm:
        held = int(statm.read().split()[0]) * resource.getpagesize()
    limit = held + mem_mb * 2**20
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    print("ready", flush=True)
    for line in sys.stdin:
        path = line.rstrip("\n")
        outcome, detail = "accepted", ""
        signal.setitimer(signal.ITIMER_REAL, timeout_s)
        try:
            target(Path(path))
        except _Hang as err:
            outcome, detail = "hang", str(err)
        except MemoryError:
            outcome, detail = "memory", f"allocated more than {mem_mb} MB"
        except errors as err:
            text = str(err)
            if "\n" in text.strip() or (path not in text and Path(path).name not in text):
                outcome, detail = "exception", f"{type(err).__name__} message is not one line naming the file: {text!r}"
            else:
                outcome, detail = "refused", text
        except BaseException as err:  # noqa: BLE001  (everything else is an escape)
            outcome, detail = "exception", f"{type(err).__name__}: {err}"[:2000]
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
        print(json.dumps({"outcome": outcome, "detail": detail}), flush=True)


class _Hang(BaseException):
    """Raised by the alarm; a BaseException so a decoder's ``except Exception`` cannot swallow it."""


if __name__ == "__main__":
    _worker(sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4]))
