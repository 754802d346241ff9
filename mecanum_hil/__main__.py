"""``python -m mecanum_hil`` is the ``mecanum-hil`` command."""

from .cli import run

if __name__ == "__main__":
    run()
