"""The diagnose report, kept importable under its former name: it lives in
:mod:`mecanum_hil.identify.diagnose.report`, the last step of the diagnose package."""

from .diagnose.report import STORY_EFFECTS, diagnose_story, plot_comparison, write_report

__all__ = ["STORY_EFFECTS", "diagnose_story", "plot_comparison", "write_report"]
