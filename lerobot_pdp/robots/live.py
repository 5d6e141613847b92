"""The live ``pdp_sim`` robots of this process, by id: the ``pdp_waypoints`` teleoperator watches "its"
robot through this (as a person with a leader arm watches the follower), and the ``lerobot-record`` /
``lerobot-rollout`` hooks find the robots whose dataset features they split."""

from __future__ import annotations

import weakref
from typing import Any

LIVE: weakref.WeakValueDictionary[str, Any] = weakref.WeakValueDictionary()
