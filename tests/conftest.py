"""Shared fixtures (builders live in `tests/helpers.py`). Rank promotion raises, so shape bugs fail loudly instead of broadcasting."""

from __future__ import annotations

import jax
import pytest

jax.config.update("jax_numpy_rank_promotion", "raise")

from mvpose_jax.data.calibration import PRESETS, load_preset  # noqa: E402
from tests.helpers import random_rig  # noqa: E402


@pytest.fixture(scope="session", params=PRESETS)
def preset_rig(request):
    """Each rig preset in turn."""
    return load_preset(request.param)


@pytest.fixture(scope="session")
def ring_rig():
    return random_rig()
