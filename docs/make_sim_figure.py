"""Regenerate docs/sim_realism.png: python docs/make_sim_figure.py [OUT.png]."""

from __future__ import annotations

import sys
from pathlib import Path

from asgp_ros.sim.figure import make_realism_figure

if __name__ == "__main__":
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).with_name("sim_realism.png")
    print(make_realism_figure(out))
