"""The ``mecanum-hil`` command line: one module per command, errors as one line.

Each command module defines one function registered here. Heavy imports (numba, OpenCV,
python-can, matplotlib) happen inside the command functions, so ``--help`` stays instant.
"""


import functools
import inspect
import sys
import warnings

import typer

from ..errors import MecanumHILError, MecanumHILWarning, SessionTerminated, UsageError
from . import batch as batch_cmd
from . import calibrate_camera as calibrate_camera_cmd
from . import campaign, demo, measure_video, record, render_video, shadow, sim_robot, simulate
from . import conformance as conformance_cmd
from . import diagnose as diagnose_cmd
from . import evaluate as evaluate_cmd
from . import export as export_cmd
from . import fit as fit_cmd
from . import fleet_report as fleet_report_cmd
from . import import_ as import_cmd
from . import measure_pose as measure_pose_cmd
from . import train as train_cmd
from ._options import check_one_of, fill_optional_values, point_at_devnull

_COMMANDS = {
    "simulate": simulate.command,
    "demo": demo.command,
    "fit": fit_cmd.command,
    "diagnose": diagnose_cmd.command,
    "measure-video": measure_video.command,
    "render-video": render_video.command,
    "record": record.command,
    "sim-robot": sim_robot.command,
    "conformance": conformance_cmd.command,
    "campaign": campaign.command,
    "shadow": shadow.command,
    "batch": batch_cmd.command,
    "fleet-report": fleet_report_cmd.command,
    "train": train_cmd.command,
    "evaluate": evaluate_cmd.command,
    "import": import_cmd.command,
    "export": export_cmd.command,
    "measure-pose": measure_pose_cmd.command,
    "calibrate-camera": calibrate_camera_cmd.command,
}


def _root(
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks of errors."),
) -> None:
    """Hardware-in-the-loop bridge and data acquisition for Mecanum-wheeled robots."""


def build_app(names=None, *, listing: bool = False) -> typer.Typer:
    """The command-line app with the commands ``names`` (default: all, in the table's order).

    typer inspects every registered command's signature on each run (~0.02-0.06 s for all of
    them here): :func:`main` registers only the command it was asked for, and with
    ``listing`` (no command named: the root's help, or an unknown command's error) each
    command as its name and help text alone, which is all the root's help shows (the same
    text, tested). The cli modules do not import ``annotations`` from ``__future__``: typer
    would evaluate each annotation string twice a run (0.15 s more on ``--help``).
    """
    application = typer.Typer(
        name="mecanum-hil",
        help="Hardware-in-the-loop bridge and data acquisition for Mecanum-wheeled robots.",
        no_args_is_help=True,
        add_completion=False,
        pretty_exceptions_enable=False,
        # plain click help: rich's formatter costs ~70 ms of start-up on every --help
        rich_markup_mode=None,
        context_settings={"help_option_names": ["-h", "--help"]},
    )
    application.callback()(_root)
    for name in names or _COMMANDS:
        if listing:
            application.command(name, help=inspect.getdoc(_COMMANDS[name]))(_listed)
        else:
            application.command(name)(_interrupt_passes_typer(_COMMANDS[name], name))
    return application


class _Interrupted(BaseException):
    """Ctrl-C in a command, carried past typer (which turns KeyboardInterrupt into a silent
    exit 130) to :func:`main`, which says so in one line."""


def _interrupt_passes_typer(fn, name: str):
    """``fn`` with a Ctrl-C it did not handle raised as :class:`_Interrupted` (its ``finally``
    clauses have run by then); a command that handles Ctrl-C itself (``record``) prints how
    the run ended, then raises it again, so that it ends as every command does. Before ``fn``
    runs, the options of which command ``name`` takes exactly one are checked
    (:func:`check_one_of`)."""
    @functools.wraps(fn)
    def command(*args, **kwargs):
        check_one_of(name, kwargs)
        try:
            return fn(*args, **kwargs)
        except KeyboardInterrupt as err:
            raise _Interrupted() from err
    return command


def _listed() -> None:
    """Stand-in for a command in the root's listing (never run: a named command is built)."""


#: Every command (tests and ``python -m mecanum_hil`` help use it).
app = build_app()


def _command_name(args: list[str]) -> str | None:
    """The command named in ``args`` (the first word after the root's options), if any."""
    for arg in args:
        if arg == "--debug":
            continue
        return arg if arg in _COMMANDS else None
    return None


def _say(line: str) -> None:
    """Print one line on stderr where it may be closed (``... 2>&1 | head -1``): the exit
    code must stay the one the line explains (a lost link is 4, not Python's 1 for a broken
    pipe at exit). What cannot be printed is dropped and stderr points at the null device
    from then on."""
    try:
        print(line, file=sys.stderr)
        sys.stderr.flush()
    except (OSError, ValueError):  # EPIPE, EIO (a hung-up terminal), a closed stream
        point_at_devnull(sys.stderr)


def _warning_printer(previous):
    """``warnings.showwarning`` printing the package's warnings as one ``warning:`` line."""
    def show(message, category, *args, **kwargs) -> None:
        if issubclass(category, MecanumHILWarning):
            _say(f"warning: {message}")
        else:
            previous(message, category, *args, **kwargs)
    return show


def main(argv: list[str] | None = None) -> int:
    """Run the CLI and return its exit code.

    The package's own errors become ``error: ...`` on stderr and their ``exit_code``; usage
    errors (an option's value, an unknown option, a missing argument, click's or the
    package's :class:`UsageError`) too, with exit 2 and where to find the command's help; an
    unexpected exception is one line too (exit 70), with the traceback behind ``--debug``.
    Commands end with other codes through ``typer.Exit``.
    """
    import errno

    click_error, no_args_error = _click_exceptions()
    args = fill_optional_values(sys.argv[1:] if argv is None else list(argv))
    debug = "--debug" in args
    name = _command_name(args)
    previous = _terminate_as_exception()
    try:
        with warnings.catch_warnings():
            # what was done to the data (time repaired on reading ...): one line each, always
            warnings.simplefilter("always", MecanumHILWarning)
            warnings.showwarning = _warning_printer(warnings.showwarning)
            app_ = build_app([name]) if name else build_app(listing=True)
            # not standalone: click's usage errors come here as exceptions (standalone, they
            # were a four-line usage block), typer.Exit(code) as the return value
            rv = app_(args=args, prog_name="mecanum-hil", standalone_mode=False)
        return rv if isinstance(rv, int) and not isinstance(rv, bool) else 0
    except no_args_error as err:
        err.show()  # the command's help: asked for by giving nothing
        return err.exit_code
    except click_error as err:
        where = f" (see '{err.ctx.command_path} --help')" if getattr(err, "ctx", None) else ""
        _say("error: " + " ".join(err.format_message().split()) + where)
        return err.exit_code
    except typer.Abort:
        _say("error: aborted")
        return 1
    except SystemExit as exit_:
        code = exit_.code
        return code if isinstance(code, int) else (0 if code is None else 1)
    except MecanumHILError as err:
        if debug:
            raise
        where = f" (see 'mecanum-hil {name} --help')" if isinstance(err, UsageError) else ""
        _say(f"error: {err}{where}")
        return err.exit_code
    except (KeyboardInterrupt, _Interrupted):
        _say("error: interrupted")
        return 130
    except SessionTerminated as err:
        _say("error: terminated by a signal")
        return err.exit_code
    except OSError as err:
        if err.errno != errno.EPIPE:
            return _internal_error(err, debug)
        point_at_devnull(sys.stdout)  # a closed pipe on stdout (``... | head``): said nowhere
        return 1
    except Exception as err:  # a bug: still one line, the traceback behind --debug
        return _internal_error(err, debug)
    finally:
        _restore_handlers(previous)


def _terminate_as_exception() -> dict:
    """SIGTERM and SIGHUP (a closed terminal) raise :class:`SessionTerminated` in the main
    thread, as Ctrl-C raises KeyboardInterrupt: the ``finally`` clauses that remove a
    temporary file, keep a previous output or close a cluster run (the default handlers end
    the process where it stands, leaving ``.tmp`` files and truncated videos). ``record``
    installs its own, which send STOP. Returns the handlers replaced."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return {}

    def terminate(signum, frame):
        raise SessionTerminated()

    previous = {}
    for name in ("SIGTERM", "SIGHUP"):
        sig = getattr(signal, name, None)
        if sig is None:
            continue
        try:
            if signal.getsignal(sig) in (signal.SIG_DFL, None):
                previous[sig] = signal.signal(sig, terminate)
        except (OSError, ValueError):
            pass
    return previous


def _restore_handlers(previous: dict) -> None:
    import signal

    for sig, handler in previous.items():
        try:
            signal.signal(sig, handler)
        except (OSError, ValueError):
            pass


def _click_exceptions() -> tuple[type[Exception], type[Exception]]:
    """Click's ``ClickException`` and ``NoArgsIsHelpError`` as the installed typer raises
    them (typer 0.28 carries its own copy of click, older ones use click itself)."""
    click_error = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "ClickException")
    no_args = getattr(sys.modules[click_error.__module__], "NoArgsIsHelpError", None)
    return click_error, no_args or _NeverRaisedError


class _NeverRaisedError(Exception):
    """Stands for an exception class a click version does not have."""


def _internal_error(err: Exception, debug: bool) -> int:
    if debug:
        raise err
    _say(f"error: internal error: {type(err).__name__}: {err} (run with --debug for the "
         "traceback, and please report it)")
    return 70


#: Commands that only read inputs, compute and write their outputs through closed files: they
#: end without the interpreter's teardown (:func:`run`).
_QUICK_EXIT = frozenset({"diagnose", "fit", "simulate"})


def run() -> None:
    """Console-script entry point.

    ``diagnose``, ``fit`` and ``simulate`` (:data:`_QUICK_EXIT`) end with ``os._exit`` once
    the exit handlers have run (a diagnosis's helper process closed) and the output is
    flushed: the interpreter's own teardown of numba's compiled code took 0.3 s after the
    last line of every such command (docs/benchmarks/diagnose.md). Each writes
    its files through ``with`` blocks closed before it returns, so nothing is left for the
    teardown to flush. Other commands (``record``, ``shadow`` ...) end the ordinary way.
    """
    code = main()
    if _command_name(fill_optional_values(sys.argv[1:])) in _QUICK_EXIT:
        _quick_exit(code)
    sys.exit(code)


def _quick_exit(code: int) -> None:
    """Run the exit handlers, flush stdout and stderr (what the handlers wrote too), end the
    process with ``code``."""
    import atexit
    import os

    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            if stream is not None:  # None: started with the descriptor closed (``>&-``)
                stream.flush()
        except (OSError, ValueError):  # a closed pipe (``| head -1``): nothing left to say
            pass
    os._exit(code)
