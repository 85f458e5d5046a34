"""``python -m sb3_dream.experiments``: see :mod:`sb3_dream.experiments.cli`."""

from sb3_dream.experiments.cli import main

if __name__ == "__main__":
    main()
