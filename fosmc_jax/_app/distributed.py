"""One command as N processes (``jax.distributed``): joining them, checking that they run the
same command, and, for the command line, a supervisor that turns a process that never joins or
dies mid-run into one line on stderr.

Every process runs the same command on the same config; the candidates of ``front`` and
``tune``'s global stage, ``tune``'s rollouts and a ``simulate`` batch are split over every
device of every process (:mod:`fosmc_jax._simulator.sharding`), every process gets all the
results back and takes the same decisions (a decision from a clock is process 0's:
:func:`fosmc_jax._simulator.sharding.first`), and process 0 alone prints and writes.

Faults. JAX ends a process whose coordinator went away, or whose peer stopped sending
heartbeats (:data:`HEARTBEAT_S`), by aborting it with many lines of C++ log; a collective whose
peer died raises at once. The command line therefore runs each process's work in a child of
its own (:func:`supervise`): the child says when it has joined and when a collective failed,
the parent forwards the child's output without JAX's C++ log, ends a child that has not joined
within ``--join-timeout`` seconds, and says in one line which process is missing or stopped.
The ``run_*`` functions join the same way but without the parent: a fault there ends the
process as JAX ends it (non-zero).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

from .._io import jsonable
from .._problems import ConfigError

#: ``--join-timeout``'s default, s: JAX's own (300 s) is long for a run typed at a terminal.
JOIN_TIMEOUT_S = 120.0
#: Seconds without a heartbeat after which JAX declares a process dead (its default: 100 s):
#: the others end within about this long of a death (at once where they wait on a collective).
HEARTBEAT_S = 60
#: The environment variable that marks a supervised child (:func:`supervise`).
CHILD = "FOSMC_DISTRIBUTED_CHILD"
#: The prefix of the child's messages to its parent (never shown).
_TELL = "\x1bfosmc-distributed:"


class Processes(NamedTuple):
    """How a command's process joins the others: ``distributed`` (``jax.distributed.initialize()``
    finds SLURM or Open MPI by itself) or ``coordinator`` ``HOST:PORT`` with ``num_processes``
    and this ``process_id``; ``join_timeout`` seconds for all of them to join."""

    distributed: bool = False
    coordinator: str | None = None
    num_processes: int | None = None
    process_id: int | None = None
    join_timeout: float = JOIN_TIMEOUT_S

    @property
    def asked(self) -> bool:
        return self.distributed or any(v is not None for v in (self.coordinator, self.num_processes, self.process_id))

    def checked(self) -> Processes:
        """Itself, or a one-line :class:`ConfigError` naming the option that is wrong."""
        if not self.asked:
            return self
        given = [n for n, v in (("--coordinator", self.coordinator), ("--num-processes", self.num_processes),
                                ("--process-id", self.process_id)) if v is not None]  # fmt: skip
        if self.distributed and given:
            raise ConfigError(f"--distributed: finds the processes by itself (SLURM, Open MPI): leave out "
                              f"{', '.join(given)}")  # fmt: skip
        if not self.distributed and len(given) < 3:
            missing = sorted({"--coordinator", "--num-processes", "--process-id"} - set(given))
            raise ConfigError(f"{given[0]}: needs {' and '.join(missing)} too (or --distributed under SLURM or "
                              "Open MPI)")  # fmt: skip
        if not self.distributed:
            host, _, port = str(self.coordinator).rpartition(":")
            if not host or not port.isdigit() or not 0 < int(port) < 65536:
                raise ConfigError(f"--coordinator: expected HOST:PORT (process 0's host), got {self.coordinator!r}")
            if not (_integer(self.num_processes) and self.num_processes >= 1):
                raise ConfigError(f"--num-processes: expected a positive integer, got {self.num_processes!r}")
            if not (_integer(self.process_id) and 0 <= self.process_id < self.num_processes):
                raise ConfigError(f"--process-id: expected an integer in [0, {self.num_processes - 1}], "
                                  f"got {self.process_id!r}")  # fmt: skip
        t = self.join_timeout
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not (math.isfinite(t) and t > 0):
            raise ConfigError(f"--join-timeout: expected a positive number of seconds, got {t!r}")
        return self


def _integer(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def join(processes: Processes) -> bool:
    """Join the other processes (``jax.distributed.initialize``) when ``processes`` asks to, and
    return whether the run spans several. Must come before JAX computes anything in this
    process: otherwise a one-line :class:`ConfigError`. A process already joined (an earlier
    ``run_*`` call) stays joined."""
    import jax

    processes = processes.checked()
    if not processes.asked:
        return False
    if jax.distributed.is_initialized():
        return jax.process_count() > 1
    option = "--distributed" if processes.distributed else "--coordinator"
    kwargs = {} if processes.distributed else dict(coordinator_address=processes.coordinator,
                                                   num_processes=processes.num_processes,
                                                   process_id=processes.process_id)  # fmt: skip
    # under the supervisor its own timer ends the wait (with a line naming who is missing): JAX's comes later
    timeout = math.ceil(processes.join_timeout) + (60 if os.environ.get(CHILD) else 0)
    try:
        jax.distributed.initialize(**kwargs, initialization_timeout=timeout, heartbeat_timeout_seconds=HEARTBEAT_S)
    except (RuntimeError, ValueError, TypeError) as e:
        if "must be called before" in str(e):  # JAX's own check that no backend has started yet
            raise ConfigError(
                f"{option}: JAX has already computed in this process: joining other processes must "
                "come first (call run_front/run_tune/run_simulate with it in a fresh process)"
            ) from None
        raise ConfigError(f"{option}: {str(e).strip().splitlines()[0]}") from None
    _tell(f"joined {jax.process_index()} {jax.process_count()}")
    return jax.process_count() > 1


def digest(options: dict[str, Any], files: tuple[str | Path | None, ...] = ()) -> bytes:
    """What must be the same on every process of a run: the resolved config and the options
    (``options``, JSON-able), and the contents of the ``files`` the run reads (a missing file
    counts as such): a SHA-256."""
    h = hashlib.sha256(json.dumps(jsonable(options), sort_keys=True, default=str).encode())
    for f in files:
        path = None if f is None else Path(f)
        h.update(b"\0" + (path.read_bytes() if path is not None and path.is_file() else b"<none>"))
    return h.digest()


@contextlib.contextmanager
def agreeing(across: bool) -> Iterator[Callable[[bytes], None]]:
    """The checks of a run's inputs, then ``agree(digest)`` (:func:`digest`) inside the block:
    every process's digest is compared with process 0's before any work, and a process whose
    checks failed (an exception in the block before ``agree``) tells the others, so
    that every process of the run ends with one line: its own error, or which process differs
    or refused. Nothing happens in one process."""
    state = {"agreed": not across}

    def agree(mine: bytes) -> None:
        if not state["agreed"]:
            state["agreed"] = True
            _compare(mine, failed=False)

    try:
        yield agree
    except Exception:  # a ConfigError, or any other error of the checks (a file that cannot be read)
        if not state["agreed"]:
            state["agreed"] = True
            _compare(b"\0" * 32, failed=True)
        raise


def _compare(mine: bytes, failed: bool) -> None:
    import jax
    import numpy as np
    from jax.experimental import multihost_utils

    row = np.frombuffer(bytes([int(failed)]) + mine, np.uint8)
    rows = np.asarray(multihost_utils.process_allgather(row), np.uint8).reshape(jax.process_count(), -1)
    if failed:
        return  # this process raises its own error
    me = jax.process_index()
    refused = [i for i in range(len(rows)) if rows[i, 0]]
    if refused:
        raise ConfigError(f"process {_names(refused)} refused the run (its error says why): every process ends")
    differ = [i for i in range(1, len(rows)) if not np.array_equal(rows[i], rows[0])]
    if me in differ:
        raise ConfigError(f"process {me}: its config, options or input files differ from process 0's: every "
                          "process must run the same command (only --process-id differs): refused")  # fmt: skip
    if differ:
        raise ConfigError(f"process {_names(differ)} was started with another config, options or input files than "
                          "process 0: refused, every process ends")  # fmt: skip


def _names(ids: list[int]) -> str:
    return ", ".join(map(str, ids))


def _tell(message: str) -> None:
    """A message to the supervising parent (:func:`supervise`), if there is one."""
    if os.environ.get(CHILD):
        print(f"{_TELL}{message}", file=sys.stderr, flush=True)


def collective_failed(e: BaseException) -> bool:
    """Whether ``e`` is a failed collective with another process (gloo's, MPI's, the
    coordination service's): a peer died."""
    text = str(e)
    return any(k in text for k in ("Gloo", "gloo", "Connection closed by peer", "Connection reset by peer",
                                   "coordination service", "UNAVAILABLE", "heartbeat"))  # fmt: skip


def after_collective_failed(e: BaseException) -> int:
    """In a supervised child, a collective failed: tell the parent and wait for JAX's verdict on
    which process died (the parent names it and ends this one); unsupervised, one line and
    status 1."""
    if os.environ.get(CHILD):
        _tell("collective-failed " + " ".join(str(e).split())[:300])
        time.sleep(HEARTBEAT_S + 30)  # the parent ends this process first
    print(f"fosmc: error: a collective with the other processes failed (one of them stopped?): "
          f"{' '.join(str(e).split())[:300]}", file=sys.stderr, flush=True)  # fmt: skip
    return 1


# ---------------------------------------------------------------------------- the supervisor

#: Lines of JAX's C++ log (absl: severity, date, time, thread, file:line), its stack traces and gloo's.
_NOISE = re.compile(r"^([IWEF]\d{4} \d\d:\d\d:\d\d\.\d+ +\d+ \S+:\d+\]|\s+@\s+0x|\*\*\* |\[Gloo\]|terminate called|"
                    r"  what\(\):)")  # fmt: skip
#: Lines of ours, that end a block of JAX's C++ log's continuation lines.
_OURS = re.compile(r"^(fosmc|front:|tune:|Traceback|  File |\w+Error|\w+Warning)")


def supervise(argv: list[str], processes: Processes) -> int:
    """Run ``fosmc argv`` as a child of this process and return its exit status, forwarding its
    stdout as it is and its stderr without JAX's C++ log. The faults of a run across processes
    become one line on stderr and status 1: a child not joined within ``join_timeout`` s is
    ended (naming the processes missing: with two, the other one; process 0's port refusing
    connections: process 0); a child whose peer died (a failed collective, JAX's heartbeat or a
    coordinator gone) is ended naming it. Ctrl-C reaches the child (the terminal's process
    group), which ends as the command does."""
    env = dict(os.environ, **{CHILD: "1"})
    child = subprocess.Popen([sys.executable, "-m", "fosmc_jax._app.cli", *argv], env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, preexec_fn=_die_with_parent)  # fmt: skip
    state: dict[str, Any] = {"joined": None, "failed": None, "log": []}
    reader = threading.Thread(target=_forward, args=(child, state), daemon=True)
    reader.start()
    printer = threading.Thread(target=_forward_stdout, args=(child, state), daemon=True)
    printer.start()
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)  # the child gets it and ends as it does
    try:
        deadline = time.monotonic() + processes.join_timeout
        verdict = None
        while child.poll() is None:
            if state["joined"] is None and time.monotonic() > deadline:
                verdict = _not_joined(processes)
                break
            if state["failed"] is not None and state["joined"] is not None:
                verdict = _who_died(state, wait=True)
                if verdict is not None:
                    break
            time.sleep(0.2)
        if verdict is None and child.poll() is not None:
            reader.join(timeout=5)
            printer.join(timeout=5)
            code = child.returncode
            if code in (0, 1, 2, 130, 141) and state["failed"] is None:
                return 141 if state.get("broken_pipe") else code
            if code < 0 and not state["log"] and state["failed"] is None:  # killed itself, JAX said nothing
                verdict = f"this process's work ended by signal {-code} ({signal.Signals(-code).name})"
            else:
                verdict = _who_died(state, wait=False) or (_not_joined(processes) if state["joined"] is None else None)
            if verdict is None:
                return code if code > 0 else 1
        if child.poll() is None:
            child.kill()
            child.wait()
        reader.join(timeout=5)
        printer.join(timeout=5)  # the child's last lines of stdout before the verdict
        print(f"fosmc: error: {verdict}", file=sys.stderr, flush=True)
        return 1
    finally:
        signal.signal(signal.SIGINT, previous)


def _die_with_parent() -> None:
    """In the child, before it runs: end it (SIGKILL) when its parent dies (Linux), so that
    killing the command kills its work."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _forward_stdout(child: subprocess.Popen, state: dict) -> None:
    """Copy the child's stdout to ours as it is, less gloo's line on its connections (which
    would break ``--json``); once our reader has gone (``| head``), read on and drop it, so
    that the child never blocks on a full pipe."""
    out = sys.stdout.buffer
    for raw in child.stdout:
        if raw.startswith(b"[Gloo] ") or state.get("broken_pipe"):
            continue
        try:
            out.write(raw)
            out.flush()
        except BrokenPipeError:
            state["broken_pipe"] = True


def _forward(child: subprocess.Popen, state: dict) -> None:
    """Copy the child's stderr to ours line by line, without JAX's C++ log (kept in
    ``state["log"]`` for :func:`_who_died`) and the child's messages (into ``state``)."""
    noise = False
    for raw in child.stderr:
        line = raw.decode(errors="replace")
        if line.startswith(_TELL):
            word, _, rest = line[len(_TELL) :].strip().partition(" ")
            state["failed" if word == "collective-failed" else word] = rest
            continue
        if _NOISE.match(line):
            noise = True
        elif noise and _OURS.match(line):
            noise = False
        if noise:
            state["log"].append(line)
            del state["log"][:-200]
            continue
        sys.stderr.write(line)
        sys.stderr.flush()


def _who_died(state: dict, wait: bool) -> str | None:
    """The one line on a dead peer, from JAX's log (a task's heartbeat timeout; the
    coordination service unreachable: process 0) or, with two processes, the other one; None
    while it is not known and ``wait``."""
    text = "".join(state["log"])
    joined = (state["joined"] or "").split()
    me, count = (int(joined[0]), int(joined[1])) if len(joined) == 2 else (None, None)
    tasks = sorted({int(t) for t in re.findall(r"[Tt]ask:? ?(\d+)\D{0,20}heartbeat", text)} - {me})
    if tasks:
        return (f"process {_names(tasks)} of {count} stopped mid-run (no heartbeat for {HEARTBEAT_S} s): this "
                f"process ({me}) ends too")  # fmt: skip
    if me != 0 and re.search(r"Socket closed|Connection refused|failed to connect|UNAVAILABLE", text):
        return f"process 0 of {count} (the coordinator) stopped mid-run: this process ({me}) ends too"
    if count == 2 and state["failed"] is not None:
        return (f"process {1 - me} of 2 stopped mid-run (a collective with it failed: {state['failed'][:120]}): "
                f"this process ({me}) ends too")  # fmt: skip
    return None if wait else ("a process of this run stopped mid-run (JAX's log: "
                              f"{' '.join(text.split())[-200:] or 'none'}): this process ends too")  # fmt: skip


def _not_joined(processes: Processes) -> str:
    """The one line on processes that did not join within the timeout."""
    t = f"{processes.join_timeout:g} s"
    if processes.distributed:
        return f"--join-timeout: the processes of this job did not all join within {t} (--distributed)"
    me, n = processes.process_id, processes.num_processes
    host, _, port = processes.coordinator.rpartition(":")
    if me != 0 and not _listening(host.strip("[]"), int(port)):
        return f"--join-timeout: process 0 (the coordinator, {processes.coordinator}) did not start within {t}"
    others = [i for i in range(n) if i != me and (me == 0 or i != 0)] or [0]
    which = f"process {others[0]}" if len(others) == 1 else f"one or more of processes {_names(others)}"
    return f"--join-timeout: {which} of {n} did not join within {t}"


def _listening(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=2.0):
            return True
    except OSError:
        return False
