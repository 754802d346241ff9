"""The protocol document is enough: a controller written from drivers/protocol.md alone
(``independent_controller.py``, which imports nothing of mecanum_hil) passes ``mecanum-hil
conformance`` and serves ``mecanum-hil record``."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from controller_checks import (
    ControllerProcess,
    conformance,
    outcomes,
    passes_every_rule,
    record_ends_with_stop,
)

CONTROLLER = Path(__file__).with_name("independent_controller.py")

class IndependentController(ControllerProcess):
    """The independent controller in its own process, serving on a pseudo-terminal."""

    def __init__(self, *args: str) -> None:
        super().__init__([sys.executable, str(CONTROLLER), *args])


@pytest.mark.slow
def test_independent_controller_passes_every_rule(tmp_path):
    passes_every_rule(tmp_path, IndependentController())


def test_e_stop_rules_with_the_e_stop_pressed(tmp_path):
    with IndependentController("--estop-pressed") as ctl:
        code, report = conformance(tmp_path, ctl.path, "--estop-pressed", "--rule", "estop")
    assert code == 0, report
    # the e-stop rules run first; once estop.reset cleared it, estop.harmless runs too
    assert outcomes(report) == {"estop.harmless": "pass", "estop.held": "pass",
                                 "estop.reset": "pass"}


def test_e_stop_reset_while_the_button_is_held_skips(tmp_path):
    # ERROR 3 answers an ESTOP_RESET at once and does not acknowledge it: the rule must see
    # the ERROR (it used to read past it waiting for the ack, and failed)
    with IndependentController("--estop-pressed", "--estop-held-s", "600") as ctl:
        code, report = conformance(tmp_path, ctl.path, "--estop-pressed", "--rule", "estop")
    assert code == 0, report
    assert outcomes(report) == {"estop.harmless": "skip", "estop.held": "pass",
                                 "estop.reset": "skip"}
    assert "ERROR 3" in report["rules"][1]["detail"], report


def test_record_against_the_independent_controller_ends_with_stop(tmp_path):
    record_ends_with_stop(tmp_path, IndependentController())
