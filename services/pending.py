"""Entry points of the distributed services that this release does not ship yet."""

from __future__ import annotations

import sys


def not_available(name: str) -> int:
    print(f"{name}: the distributed services are not part of this release yet; train in one "
          "process with `tpdeb-train --env-id ENV` (see README.md).", file=sys.stderr)
    return 2
