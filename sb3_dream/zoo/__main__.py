"""``python -m sb3_dream.zoo train|enjoy|record_video ...``: see :mod:`sb3_dream.zoo.cli`."""

from sb3_dream.zoo.cli import main

main()
