"""The embedded Ray is started with usage statistics off unless the user opted in."""

from __future__ import annotations

import os

from services.training.job import embedded_ray_defaults


def test_usage_stats_off_when_unset(monkeypatch):
    monkeypatch.delenv("RAY_USAGE_STATS_ENABLED", raising=False)
    embedded_ray_defaults()
    assert os.environ["RAY_USAGE_STATS_ENABLED"] == "0"


def test_a_users_choice_is_kept(monkeypatch):
    monkeypatch.setenv("RAY_USAGE_STATS_ENABLED", "1")
    embedded_ray_defaults()
    assert os.environ["RAY_USAGE_STATS_ENABLED"] == "1"
