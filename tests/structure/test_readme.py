"""The README's commands run as written after its quick start."""

from __future__ import annotations


def test_venv_is_activated_before_the_first_bare_command(repo):
    lines = (repo / "README.md").read_text(encoding="utf-8").splitlines()
    fenced, in_block = [], False
    for i, line in enumerate(lines):
        if line.startswith("```"):
            in_block = not in_block
        elif in_block:
            fenced.append((i, line))
    install = next(i for i, line in fenced if ".venv/bin/pip install" in line)
    bare = next(i for i, line in fenced if line.startswith("mecanum-hil "))
    activate = next((i for i, line in enumerate(lines) if ". .venv/bin/activate" in line), -1)
    assert install < activate < bare, "say how to activate the venv before `mecanum-hil ...`"
