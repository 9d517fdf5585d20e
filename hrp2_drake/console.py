"""The console of a run: one format for every line it prints on stderr, and each
repeated warning printed once, then counted.

Every line is

    <program>: [<context>: ][<level>: ]<message>

like the command's own error line (`hrp2-drake reproduce: error: ...`): the program
(`hrp2-drake reproduce`), the part of the run that wrote it when several run at once
(`motion` in a worker of `reproduce`), the level for warnings and errors (not for
progress), then the message. `line` formats one; `run_with_progress` and the
logging handler of `session` use it.

A simulation can log the same warning thousands of times (a torque controller that
falls back at every tick after its supervisor resumed it). `session` prints the
first record of each message *template* (the message with its numbers taken out:
the same system, the same reason, another time) and counts the others; when the
session ends it prints one line per repeated template, "repeated N more times".
A worker process of `reproduce` runs each step in a session of its own, returns its
counts (`Session.repeats()`) with the step's results, and the parent adds them to its
session (`Session.add_repeats`), which prints them at the end of the run. The workers
of a process pool get a session for their life with `start_worker`.

Outside a session (a library call, a test) nothing is configured: Python's logging
prints warnings as usual and progress lines have no program prefix.
"""

import contextlib
import logging
import re
import sys
from collections.abc import Iterator

#: The program and context of the current session (empty: none), and the session.
_PROGRAM = ""
_CONTEXT = ""
_SESSION: "Session | None" = None

#: A number in a message: signed, decimal or exponent; not a digit of a name
#: (RLEG_JOINT4, K6, ::_::) nor of a version.
_NUMBER = re.compile(r"(?<![\w.])[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?(?![\w.])")
#: Where a template has a number.
NUMBER_MARK = "…"


def line(message: str, level: str = "") -> str:
    """One console line: `<program>: [<context>: ][<level>: ]<message>` (the
    program and context of the current session, if any)."""
    parts = [p for p in (_PROGRAM, _CONTEXT, level) if p]
    return ": ".join(parts + [message])


def say(message: str, stream=None) -> None:
    """Writes `line(message)` and its newline to `stream` (stderr) in one write, and
    flushes: the lines of processes that share the stream (the workers of
    `reproduce`) stay whole, even unbuffered (PYTHONUNBUFFERED)."""
    stream = stream or sys.stderr
    stream.write(line(message) + "\n")
    stream.flush()


def template(message: str) -> str:
    """The message with each number replaced by NUMBER_MARK: what its repeats share."""
    return _NUMBER.sub(NUMBER_MARK, message)


def one_line(message: str) -> str:
    """The message's lines joined by a space (a Python warning has its source line
    on a second one)."""
    return " ".join(
        part.strip() for part in message.strip().splitlines() if part.strip()
    )


class _Formatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        message = record.getMessage()
        if record.exc_info:  # one line: the exception's type and message
            error = record.exc_info[1]
            message += f" ({type(error).__name__}: {error})"
        level = "" if record.levelno < logging.WARNING else record.levelname.lower()
        return line(one_line(message), level)


class _Handler(logging.Handler):
    """Writes to the current sys.stderr (a test's capture included); shows this
    project's progress (INFO of `hrp2_drake.*`) and everyone's warnings; lets the
    first record of each template through and counts the others."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.setFormatter(_Formatter())
        self.counts: dict[str, int] = {}  # template -> records after the first

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.WARNING and not record.name.startswith(
            "hrp2_drake"
        ):
            return False
        if record.levelno < logging.WARNING:
            return True  # progress is never counted
        key = f"{record.levelname.lower()}: {template(one_line(record.getMessage()))}"
        if key in self.counts:
            self.counts[key] += 1
            return False
        self.counts[key] = 0
        return True

    def emit(self, record: logging.LogRecord) -> None:
        try:
            sys.stderr.write(self.format(record) + "\n")
            sys.stderr.flush()
        except Exception:
            self.handleError(record)


class Session:
    """What `session` yields: the counts of the repeated warnings."""

    def __init__(self, handler: _Handler) -> None:
        self._handler = handler
        self._added: list[tuple[str, dict[str, int]]] = []

    def repeats(self) -> dict[str, int]:
        """{"<level>: <template>": records after the first} of this process, for the
        templates that repeated."""
        return {key: n for key, n in self._handler.counts.items() if n > 0}

    def add_repeats(self, repeats: dict[str, int], context: str = "") -> None:
        """Counts of another process (a worker's part of the run, its `repeats()`)
        to print at the end of this session, under `context`."""
        if repeats:
            self._added.append((context, dict(repeats)))


def print_repeats(repeats: dict[str, int], context: str = "", stream=None) -> None:
    """One line per repeated template, `<program>: [<context>: ]<level>: repeated N
    more times: <template>`."""
    stream = stream or sys.stderr
    for key, n in repeats.items():
        level, _, text = key.partition(": ")
        words = f"repeated {n} more {'time' if n == 1 else 'times'}: {text}"
        stream.write(
            ": ".join([p for p in (_PROGRAM, context, level) if p] + [words]) + "\n"
        )
    stream.flush()


@contextlib.contextmanager
def session(program: str, context: str = "", summary: bool = True) -> Iterator[Session]:
    """Installs the console for the run of `program` (and `context`, the part of
    the run this process does): every line in one format (`line`), this project's
    INFO lines shown, Python warnings logged, each repeated warning printed once and
    counted. On exit, with `summary`, prints the counts (`print_repeats`: this
    process's, then those added); then restores the logging configuration."""
    global _PROGRAM, _CONTEXT, _SESSION
    root, ours = logging.getLogger(), logging.getLogger("hrp2_drake")
    handler = _Handler()
    state = Session(handler)
    saved = (_PROGRAM, _CONTEXT, _SESSION, ours.level)
    _PROGRAM, _CONTEXT, _SESSION = program, context, state
    root.addHandler(handler)
    ours.setLevel(logging.INFO)
    logging.captureWarnings(True)
    try:
        yield state
    finally:
        logging.captureWarnings(False)
        root.removeHandler(handler)
        if summary:
            print_repeats(state.repeats(), context)
            for where, repeats in state._added:
                print_repeats(repeats, where)
        _PROGRAM, _CONTEXT, _SESSION, level = saved
        ours.setLevel(level)


def start_worker(program: str, context: str) -> None:
    """The initializer of a worker process (`ProcessPoolExecutor(initializer=...)`):
    a session for the worker's life, under `context`, that prints its repeated
    warnings' counts when the worker exits (with its pool, at the end of the run)."""
    import atexit

    manager = session(program, context)
    manager.__enter__()
    atexit.register(manager.__exit__, None, None, None)


def program() -> str:
    """The program of the current session ("" outside one)."""
    return _PROGRAM


def current() -> Session | None:
    """The session this process runs in, or None."""
    return _SESSION
