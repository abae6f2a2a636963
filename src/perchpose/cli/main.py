"""The entry point: run a command; a user's mistake (``PerchposeError``, a file that cannot be
read or written) becomes one line on stderr and exit code 2; Ctrl-C, SIGTERM and SIGHUP unwind
the command (files closed whole, a flying vehicle landed) and exit with 128 + the signal."""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

import click

from perchpose.cli.group import group
from perchpose.errors import PerchposeError


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP, handled as Ctrl-C is: files closed whole, a flying vehicle landed."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


# the termination signals received during this run (a compiled call that a signal interrupts
# may hand back a SystemError with the interrupt anywhere in its chain, or nowhere)
_received: list[int] = []


def _terminate(signum: int, _frame: object) -> None:
    _received.append(signum)
    raise Terminated(signum)


@contextmanager
def _signals_as_interrupts() -> Iterator[None]:
    """While a command runs, SIGTERM and SIGHUP unwind it as Ctrl-C does (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    wanted = [signal.SIGTERM] + ([signal.SIGHUP] if hasattr(signal, "SIGHUP") else [])
    previous = {sig: signal.signal(sig, _terminate) for sig in wanted}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _interrupted(exc: BaseException | None) -> int:
    """Say why the run stopped; the exit code is 128 + the signal's number (Ctrl-C: 130)."""
    if isinstance(exc, Terminated):
        click.echo(f"perchpose: terminated ({exc})", err=True)
        return 128 + exc.signum
    click.echo("perchpose: interrupted", err=True)
    return 130


def main(argv: list[str] | None = None) -> int:
    """Entry point: run the command, turn library errors into one line and exit code 2."""
    _received.clear()
    try:
        with _signals_as_interrupts():
            group.main(args=argv, prog_name="perchpose", standalone_mode=False)
    except PerchposeError as exc:
        click.echo(f"perchpose: error: {exc}", err=True)
        return 2
    except OSError as exc:
        # the library wraps the files it names; this is the net for any other file trouble
        where = f"{exc.filename}: " if exc.filename else ""
        click.echo(f"perchpose: error: {where}{exc.strerror or exc}", err=True)
        return 2
    except click.exceptions.Abort as exc:
        return _interrupted(exc.__cause__)
    except click.ClickException as exc:
        exc.show()
        return exc.exit_code
    except (KeyboardInterrupt, SystemError) as exc:
        # a signal that arrives while a compiled function (numba's) calls back into Python
        # raises there, and the calls return with it as the cause of a chain of SystemErrors;
        # they have unwound the command all the same (finally blocks run for any exception)
        interrupt = exc if isinstance(exc, KeyboardInterrupt) else _interrupt_behind(exc)
        if interrupt is None and _received:
            interrupt = Terminated(_received[-1])
        if interrupt is None:
            raise
        return _interrupted(interrupt)
    return 0


def _interrupt_behind(exc: SystemError) -> KeyboardInterrupt | None:
    """The interrupt (Ctrl-C, ``Terminated``) at the root of a chain of SystemErrors, each
    the cause of the next or raised while handling it (the interpreter links a compiled
    call's pending exception either way), or None."""
    seen: set[int] = set()
    link: BaseException | None = exc
    while isinstance(link, SystemError) and id(link) not in seen:
        seen.add(id(link))
        link = link.__cause__ if link.__cause__ is not None else link.__context__
    return link if isinstance(link, KeyboardInterrupt) else None


def run() -> None:
    """Console-script entry point."""
    sys.exit(main())
