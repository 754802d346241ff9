"""A fleet's archive on Dask: fit, diagnose, shadow-replay and measure thousands of recordings.

``mecanum-hil batch`` and ``mecanum-hil fleet-report`` (docs/scale.md). The pieces, from the
edge inwards:

- :mod:`.archive`: finds the recordings (or videos) of an archive through fsspec (a folder, a
  ``file://``, ``s3://``... URL) and groups them per robot and per period.
- :mod:`.tasks`: one group as one self-contained task: stream its files to the worker's disk
  while hashing them, skip it when the hash matches the previous run, run the stage, return one
  row. Any failure stays in that row.
- :mod:`.stages`: the adapter to the library's stages (fit, diagnose, shadow replay,
  measure-video); the only module that imports them.
- :mod:`.runner`: submits the tasks to a Dask cluster (a local one by default), journals each
  row as it arrives (an interrupted batch resumes), shows the progress.
- :mod:`.results`: the results table (Parquet or CSV), drift against the previous period.
- :mod:`.report`: drift plots and a Markdown summary.

Dask, fsspec and pyarrow are the optional extra ``fleet`` (``pip install 'mecanum-hil[fleet]'``);
they are imported inside the functions that use them, so nothing here loads them on import and
the core commands never do.
"""

from __future__ import annotations

#: What to install when the extra is missing.
INSTALL_HINT = "pip install 'mecanum-hil[fleet]'"


def require_extra(module: str):
    """Import one of the extra's modules, or raise a one-line ConfigError saying what to install.

    Parameters
    ----------
    module : str
        ``"dask.distributed"``, ``"fsspec"``, ``"pyarrow.parquet"`` ...
    """
    import importlib

    from ..errors import ConfigError

    try:
        return importlib.import_module(module)
    except ImportError as err:
        raise ConfigError(f"this needs {module.split('.')[0]} (the fleet extra: "
                          f"{INSTALL_HINT}): {err}") from err
