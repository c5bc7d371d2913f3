"""Where the real recordings made by others lie: `$ODSPLAT_SHARED_DATA`, else `shared/data` beside the checkout (its
README says what each is). One rule for the tests, the benches and the demo, which skip or say so without them."""
from __future__ import annotations

import os
from pathlib import Path

SHARED_DATA_ENV = "ODSPLAT_SHARED_DATA"


def shared_data_dir(beside: Path) -> Path:
    """$ODSPLAT_SHARED_DATA where it is set, else `beside`'s neighbour shared/data (`beside`: a checkout's root).
    Whether it exists is the caller's to ask."""
    env = os.environ.get(SHARED_DATA_ENV)
    return Path(env) if env else Path(beside).parent / "shared" / "data"


__all__ = ["SHARED_DATA_ENV", "shared_data_dir"]
