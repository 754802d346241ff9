"""Every command imports only what it uses, when it uses it.

Each command's module is imported in a fresh interpreter; none of the heavy libraries may be
loaded by that import alone (they are imported inside the functions that need them), so
``mecanum-hil --help`` and every command's start-up stay fast.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

CLI = Path(__file__).resolve().parents[2] / "mecanum_hil" / "cli"

#: Libraries no command module may load at import time.
HEAVY = ("scipy", "numba", "matplotlib", "cv2", "can", "cantools", "gymnasium", "serial",
         "dask", "distributed", "rosbags", "mcap", "foxglove", "cma", "pandas", "pyarrow")

COMMAND_MODULES = sorted(
    f"mecanum_hil.cli.{p.stem}" for p in CLI.glob("*.py") if p.stem != "__init__"
)


def _loaded_after_import(module: str) -> list[str]:
    code = (
        "import importlib, json, sys\n"
        f"importlib.import_module({module!r})\n"
        "print(json.dumps(sorted({m.split('.')[0] for m in sys.modules})))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("module", ["mecanum_hil.cli", *COMMAND_MODULES])
def test_command_module_loads_no_heavy_library(module):
    loaded = set(_loaded_after_import(module))
    heavy = sorted(loaded.intersection(HEAVY))
    assert not heavy, f"importing {module} loads {heavy}: import them where they are used"


def test_the_all_extra_holds_every_extra():
    """CI installs ``.[test,all]``: an extra left out of ``all`` would go untested."""
    import tomllib

    with open(CLI.parents[1] / "pyproject.toml", "rb") as f:
        extras = tomllib.load(f)["project"]["optional-dependencies"]
    (spec,) = extras["all"]
    named = set(spec.split("[", 1)[1].rstrip("]").split(","))
    assert named == set(extras) - {"all", "test"}


def test_command_annotations_are_evaluated_once_at_import():
    """typer reads every command's options from its annotations on each run; as strings
    (``from __future__ import annotations``) each would be evaluated twice a run, 0.15 s of
    ``--help``'s 0.22 s on the 2-core machine. The cli modules keep them objects."""
    for path in sorted(CLI.glob("*.py")):
        assert "from __future__ import annotations" not in path.read_text(), path.name


@pytest.mark.parametrize("args", [["--help"], [], ["--debug", "--help"], ["no-such-command"]])
def test_the_root_listing_says_what_the_whole_app_says(args, capsys):
    """Without a command named, main builds each command as its name and help alone (typer
    reading 19 signatures was a tenth of ``--help``): the same text and exit code as the app
    with every command."""
    from mecanum_hil import cli

    code = cli.main(args)
    listed = capsys.readouterr()
    try:
        cli.app(args=args, prog_name="mecanum-hil")
    except SystemExit as exit_:
        whole = exit_.code
    if args == ["no-such-command"]:
        # a usage error: main says it in one line (the app standalone, in a usage block)
        assert code == whole == 2 and listed.out == ""
        assert listed.err == ("error: No such command 'no-such-command'. (see 'mecanum-hil "
                              "--help')\n")
        return
    assert (code, listed.out, listed.err) == (whole, *capsys.readouterr())
    assert "measure-video" in listed.out + listed.err
