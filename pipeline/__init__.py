"""sorolearn: learned closed-loop controllers for pneumatic soft robot arms."""

from pathlib import Path

PROJECT_ROOT = Path(__file__).resolve().parent.parent  # the checkout: conf/ lies here
