"""``sb3-dream-zoo``: rl-zoo3's ``train``, ``enjoy`` and ``record_video`` with DREAM and RL2DQN.

Usage::

    sb3-dream-zoo train --algo dream --env MetaBus-v0 [any rl_zoo3.train flag]
    sb3-dream-zoo enjoy --algo dream --env MetaBus-v0 [any rl_zoo3.enjoy flag]
    sb3-dream-zoo record_video --algo dream --env MetaBus-v0 [any rl_zoo3.record_video flag]

(or ``python -m sb3_dream.zoo ...``). Before handing over to rl-zoo3 it registers the algorithms
(:func:`sb3_dream.zoo.register`) and adds defaults that the zoo's own defaults get wrong for trial
envs; a flag given on the command line always wins, as the defaults are put first:

* ``train`` with ``--algo dream|rl2_dqn``: ``--conf-file`` defaults to the packaged
  hyperparameters (:func:`sb3_dream.zoo.hyperparams_path`), as rl-zoo3 looks only inside its own
  package: the paper's, with ``--settings measured`` (this wrapper's one flag of its own) those
  of the README's measured runs, with ``--settings laptop`` DREAM's ``PRESETS["laptop"]``. With a
  trial env and no ``--eval-env-kwargs``, the zoo's evaluation (``--eval-freq``) runs on the
  held-out problems: the eval env gets ``--env-kwargs`` plus ``split:'test'``.
* ``train --optimize --storage URL --study-name S``: the study is created (or found) before
  rl-zoo3 runs, retrying while other workers create the same database, so that several workers,
  on one machine or many, add trials to one study. ``train --best-trial`` (this wrapper's flag,
  with ``--storage`` and ``--study-name``) trains with the study's best trial as ``-params``.
* ``enjoy`` / ``record_video``: ``--folder`` defaults to ``logs`` (where ``train`` writes) rather
  than the zoo's pretrained-agent folder, which would try to download from the Hugging Face hub;
  ``enjoy`` adds ``--no-render`` for envs without a "human" render mode (the trial envs render
  ``rgb_array`` only; ``record_video`` or ``examples/watch_dream.py`` write videos).
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from typing import Any, Callable, Iterator, List, Optional, Sequence, Tuple

from sb3_dream.zoo import SETTINGS, ZOO_ALGOS, hyperparams_path, register

COMMANDS = ("train", "enjoy", "record_video")
USAGE = f"""usage: sb3-dream-zoo {{{','.join(COMMANDS)}}} [rl-zoo3 flags]

rl-zoo3 with the algorithms {', '.join(ZOO_ALGOS)} and the trial envs of dream_envs.
Examples:
  sb3-dream-zoo train --algo dream --env MetaBus-v0 -n 100000 --eval-freq 10000
  sb3-dream-zoo train --algo dream --env MetaCook-v0 --settings measured   # the README's runs
  sb3-dream-zoo train --algo dream --env MetaBus-v0 --env-kwargs variant:"'map'" --settings laptop
  sb3-dream-zoo enjoy --algo dream --env MetaBus-v0 -n 400
  sb3-dream-zoo train --algo rl2_dqn --env MetaBus-v0 --optimize --n-trials 20 -n 50000
  sb3-dream-zoo train --algo dream --env MetaBus-v0 --optimize --storage sqlite:///s.db --study-name s
  sb3-dream-zoo train --algo dream --env MetaBus-v0 --best-trial --storage sqlite:///s.db --study-name s
'<command> --help' lists the command's rl-zoo3 flags."""


def _known_args(argv: Sequence[str]) -> argparse.Namespace:
    """The few flags this wrapper looks at, read without consuming or validating anything."""
    parser = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    parser.add_argument("--algo", default="ppo")
    parser.add_argument("--env", default="CartPole-v1")
    parser.add_argument("-conf", "--conf-file", default=None)
    parser.add_argument("--env-kwargs", nargs="+", default=None)
    parser.add_argument("--eval-env-kwargs", nargs="+", default=None)
    parser.add_argument("-f", "--folder", "--log-folder", dest="folder", default=None)
    parser.add_argument("--no-render", action="store_true")
    return parser.parse_known_args(list(argv))[0]


def _env_class(env_id: str) -> Optional[type]:
    """The class behind a registered env ID, or None if it cannot be told without making the env."""
    import gymnasium as gym
    from gymnasium.envs.registration import load_env_creator

    try:
        entry_point = gym.spec(env_id).entry_point
        creator = load_env_creator(entry_point) if isinstance(entry_point, str) else entry_point
    except Exception:  # unknown ID: rl-zoo3 reports it with a suggestion
        return None
    return creator if isinstance(creator, type) else None


def _is_trial_env(env_id: str) -> bool:
    from dream_envs import TrialEnv

    cls = _env_class(env_id)
    return cls is not None and issubclass(cls, TrialEnv)


def _pop_settings(argv: Sequence[str]) -> Tuple[Optional[str], List[str]]:
    """This wrapper's ``--settings paper|measured`` (rl-zoo3 does not know it) and the rest of ``argv``."""
    parser = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    parser.add_argument("--settings", default=None)
    known, rest = parser.parse_known_args(list(argv))
    if known.settings is not None and known.settings not in SETTINGS:
        raise SystemExit(
            f"sb3-dream-zoo: settings={known.settings!r} is not valid; accepted values: {', '.join(SETTINGS)}"
        )
    return known.settings, rest


def _study_args(argv: Sequence[str]) -> argparse.Namespace:
    """rl-zoo3's flags of an Optuna study in ``argv`` (``--algo``, ``--storage``, ``--study-name``,
    ``--optimize``), read without consuming or validating anything."""
    parser = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    parser.add_argument("--algo", default="ppo")
    parser.add_argument("--storage", default=None)
    parser.add_argument("--study-name", default=None)
    parser.add_argument("--optimize", "--optimize-hyperparameters", "-optimize", action="store_true")
    return parser.parse_known_args(list(argv))[0]


def _pop_best_trial(argv: Sequence[str]) -> Tuple[bool, List[str]]:
    """This wrapper's ``--best-trial`` flag and the rest of ``argv``."""
    parser = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    parser.add_argument("--best-trial", action="store_true")
    known, rest = parser.parse_known_args(list(argv))
    return known.best_trial, rest


def best_trial_args(argv: Sequence[str]) -> List[str]:
    """``argv`` with the best trial of the Optuna study ``--storage``/``--study-name`` as ``-params``
    (converted to constructor arguments as rl-zoo3's ``--trial-id`` does); the command's own
    ``-params`` win over the trial's."""
    known = _study_args(argv)
    if known.storage is None or known.study_name is None or known.optimize:
        raise SystemExit("sb3-dream-zoo: --best-trial trains with a study's best trial: give --storage and "
                         "--study-name, without --optimize")  # fmt: skip
    import optuna
    from rl_zoo3.hyperparams_opt import HYPERPARAMS_CONVERTER

    storage: Any = known.storage
    if storage.endswith(".log"):  # rl-zoo3's journal-file storage
        storage = optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(storage))
    try:
        best = optuna.load_study(study_name=known.study_name, storage=storage).best_trial
    except (KeyError, ValueError) as error:
        raise SystemExit(f"sb3-dream-zoo: no best trial in study {known.study_name!r} at {known.storage}: {error}")
    convert = HYPERPARAMS_CONVERTER.get(known.algo, dict)
    params = {key: repr(value) for key, value in convert(best.params).items()}
    rest: List[str] = []
    tokens = iter(argv)
    for token in tokens:
        if token in ("-params", "--hyperparams"):
            for value in tokens:
                if value.startswith("-") and not value[1:2].isdigit():
                    rest.append(value)  # the next flag
                    break
                key, _, given = value.partition(":")
                params[key] = given  # the command's own win
            continue
        rest.append(token)
    print(f"sb3-dream-zoo: trial {best.number} of study {known.study_name!r} (value {best.value}): {params}")
    return [*rest, "-params", *(f"{key}:{value}" for key, value in params.items())]


def create_study(argv: Sequence[str], attempts: int = 20) -> None:
    """With ``--optimize --storage URL --study-name S``: create the study (or find it) before
    rl-zoo3 does, retrying while other workers create the same database's tables at the same
    moment (a fresh SQLite file or database is otherwise a race that one of them loses)."""
    known = _study_args(argv)
    if not known.optimize or known.storage is None or known.study_name is None or known.storage.endswith(".log"):
        return
    import optuna

    for attempt in range(attempts):
        try:
            optuna.create_study(
                storage=known.storage, study_name=known.study_name, load_if_exists=True, direction="maximize"
            )
            return
        except Exception:  # noqa: BLE001  (the database's own error types; the last one is raised)
            if attempt == attempts - 1:
                raise
            time.sleep(0.2 + 0.1 * attempt)


def train_args(argv: Sequence[str]) -> List[str]:
    """``argv`` of ``train`` with this package's defaults put first (so the user's flags win)."""
    best_trial, argv = _pop_best_trial(argv)
    if best_trial:
        argv = best_trial_args(argv)
    settings, argv = _pop_settings(argv)
    known = _known_args(argv)
    if settings is not None and (known.algo not in ZOO_ALGOS or known.conf_file is not None):
        raise SystemExit(
            "sb3-dream-zoo: --settings picks the packaged --conf-file of --algo "
            f"{' or '.join(ZOO_ALGOS)}; got --algo {known.algo}"
            + (f" and --conf-file {known.conf_file}" if known.conf_file is not None else "")
        )
    defaults: List[str] = []
    if known.algo in ZOO_ALGOS and known.conf_file is None:
        try:
            defaults += ["--conf-file", str(hyperparams_path(known.algo, settings or "paper"))]
        except ValueError as error:  # e.g. --settings measured for an algorithm without measured runs
            raise SystemExit(f"sb3-dream-zoo: {error}") from error
    if known.eval_env_kwargs is None and _is_trial_env(known.env):
        env_kwargs = [kv for kv in (known.env_kwargs or []) if kv.split(":", 1)[0] != "split"]
        defaults += ["--eval-env-kwargs", *env_kwargs, "split:'test'"]
    return [*defaults, *argv]


def enjoy_args(argv: Sequence[str], render_flag: bool = True) -> List[str]:
    """``argv`` of ``enjoy``/``record_video`` with this package's defaults put first."""
    known = _known_args(argv)
    defaults: List[str] = []
    if known.folder is None:
        defaults += ["--folder", "logs"]
    cls = _env_class(known.env)
    if render_flag and not known.no_render and cls is not None:
        if "human" not in getattr(cls, "metadata", {}).get("render_modes", []):
            print(
                f"sb3-dream-zoo: {known.env} has no 'human' render mode: adding --no-render "
                "(record_video or examples/watch_dream.py write videos)"
            )
            defaults.append("--no-render")
    return [*defaults, *argv]


@contextlib.contextmanager
def _argv(prog: str, args: Sequence[str]) -> Iterator[None]:
    """rl-zoo3's scripts parse ``sys.argv`` themselves."""
    saved = sys.argv
    sys.argv = [prog, *args]
    try:
        yield
    finally:
        sys.argv = saved


def main(argv: Optional[Sequence[str]] = None) -> None:
    """Entry point of ``sb3-dream-zoo`` and ``python -m sb3_dream.zoo``."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(USAGE)
        return
    command, rest = args[0], args[1:]
    if command not in COMMANDS:
        raise SystemExit(f"sb3-dream-zoo: command={command!r} is not valid; accepted values: {', '.join(COMMANDS)}")
    register()
    script: Callable[[], None]
    if command == "train":
        from rl_zoo3.train import train as script

        rest = train_args(rest)
        create_study(rest)
    elif command == "enjoy":
        from rl_zoo3.enjoy import enjoy as script

        rest = enjoy_args(rest)
    else:
        import runpy

        # rl-zoo3's record_video is a script body under ``if __name__ == "__main__"``.
        def script() -> None:
            runpy.run_module("rl_zoo3.record_video", run_name="__main__", alter_sys=True)

        rest = enjoy_args(rest, render_flag=False)
    with _argv(f"sb3-dream-zoo {command}", rest):
        script()


if __name__ == "__main__":
    main()
