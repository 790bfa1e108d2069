"""`tpdeb-learner`: not shipped in this release (see services/pending.py)."""

from services.pending import not_available


def main() -> int:
    return not_available("tpdeb-learner")
