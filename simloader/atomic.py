"""Files written whole or not at all: a reader, a resumed writer or a later process sees the
whole file or none of it, never a part left by a killed process or a full disk."""

from __future__ import annotations

import os
import uuid
from collections.abc import Sequence
from typing import Any


def atomic_write(path: str, parts: Sequence[Any]) -> None:
    """Writes `parts` (bytes-like) to `path` through a temporary file renamed over it: a
    reader or a resumed writer sees the whole file or none of it."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    temporary = f"{path}.{uuid.uuid4().hex}.partial"
    try:
        with open(temporary, "wb") as f:
            for part in parts:
                f.write(part)
        os.replace(temporary, path)
    except BaseException:
        try:
            os.unlink(temporary)
        except OSError:
            pass
        raise
