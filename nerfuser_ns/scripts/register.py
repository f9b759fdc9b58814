"""``ns-nerfuser-register``: registration from re-rendering (placeholder until the registration issue lands)."""

from __future__ import annotations

import sys


def entrypoint() -> None:
    print("ns-nerfuser-register: not implemented yet (see the project's issue tracker)", file=sys.stderr)
    sys.exit(2)


if __name__ == "__main__":
    entrypoint()
