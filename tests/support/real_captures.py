"""Where the real captures for the optional tests live: ../shared/captures beside the
checkout. Tests that use one skip when its folder is absent (CI has none)."""

from pathlib import Path

SHARED_CAPTURES = Path(__file__).resolve().parents[3] / "shared" / "captures"
