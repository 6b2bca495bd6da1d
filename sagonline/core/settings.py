"""Checking settings: one rule per key, one line naming the key when a value breaks it."""

from __future__ import annotations

import math


def check_settings(group: str, **checks: tuple[bool, object, str]) -> None:
    """Raise ValueError `group.key=value: must be <rule>` for the first check that fails.
    checks: key -> (holds, value, rule), e.g. margin=(0 <= m < 1, m, "in [0, 1)"). A float
    value that is NaN or infinite fails whatever its rule says (no setting means infinity)."""
    for key, (holds, value, rule) in checks.items():
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"{group}.{key}={value!r}: must be a finite number ({rule})")
        if not holds:
            raise ValueError(f"{group}.{key}={value!r}: must be {rule}")
