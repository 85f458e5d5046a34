"""Argument checks shared by the envs and the algorithms: each raises a ``ValueError`` that names the
argument and the values it accepts."""

from __future__ import annotations

from typing import Any, Sequence, Tuple

import numpy as np


def check_choice(name: str, value: Any, choices: Sequence[Any]) -> Any:
    """Raise a ``ValueError`` naming ``name`` and the accepted values unless ``value`` is one of them.

    Booleans only match booleans: ``1 == True`` in Python, but 1 is not an accepted ``True``.
    """
    if not any(value == c and isinstance(value, bool) == isinstance(c, bool) for c in choices):
        raise ValueError(f"{name}={value!r} is not valid; accepted values: {', '.join(map(repr, choices))}")
    return value


def check_positive_int(name: str, value: Any, minimum: int = 1) -> int:
    """Raise a ``ValueError`` naming ``name`` unless ``value`` is an integer >= ``minimum`` (not a bool)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def check_layer_sizes(name: str, value: Any) -> Tuple[int, ...]:
    """The layer sizes of a network as a tuple, or a ``ValueError`` naming ``name`` unless ``value``
    is a non-empty list or tuple of positive integers."""
    positive = lambda h: isinstance(h, (int, np.integer)) and not isinstance(h, bool) and h >= 1  # noqa: E731
    if not (isinstance(value, (list, tuple)) and len(value) > 0 and all(map(positive, value))):
        raise ValueError(f"{name} must be a non-empty list or tuple of positive ints, got {value!r}")
    return tuple(int(h) for h in value)


def check_bool(name: str, value: Any) -> bool:
    """Return ``value`` as a ``bool`` or raise a ``ValueError`` naming ``name`` unless it is True or False
    (a Python or numpy bool: 0, 1 and strings are refused)."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def check_non_negative(name: str, value: Any) -> float:
    """Raise a ``ValueError`` naming ``name`` unless ``value`` is a finite real number >= 0 (not a bool)."""
    is_real = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
    if not (is_real and np.isfinite(value) and value >= 0):
        raise ValueError(f"{name} must be a number >= 0, got {value!r}")
    return float(value)


def check_action(action: Any, n_actions: int) -> int:
    """Return ``action`` as an ``int`` or raise a ``ValueError`` naming it, unless it is an integer in
    ``0 .. n_actions - 1``: a Python or numpy integer, or an integer array of size 1 (as a vectorised
    env hands out). Booleans, floats and strings are refused rather than rounded or cast."""
    value = action
    if isinstance(value, np.ndarray) and value.size == 1:
        value = value.reshape(())[()]
    is_integer = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
    if not (is_integer and 0 <= value < n_actions):
        raise ValueError(
            f"action={action!r} is not valid; accepted values: integers 0 .. {n_actions - 1} "
            "(a Python or numpy integer, or an integer array of size 1)"
        )
    return int(value)
