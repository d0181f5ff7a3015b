"""Regenerate configs/scenarios/paper/paper.net.xml from its plain-XML sources.

Usage: .venv/bin/python configs/scenarios/build_paper.py
Uses netconvert from the eclipse-sumo package (same version as libsumo); the options
are in sumo_side.scenarios.PAPER_NETCONVERT_OPTIONS.
"""

from __future__ import annotations

import logging

from sumo_side.scenarios import PAPER_DIR, build_paper_net


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    net = build_paper_net(PAPER_DIR)
    logging.getLogger("build_paper").info("wrote %s", net)


if __name__ == "__main__":
    main()
