"""python -m experiments.atari {list,run}: the Atari experiment's GPU units (experiments/atari/units.py)."""

from experiments import launch
from experiments.atari.units import END_S, LIMIT_S, UNITS

if __name__ == "__main__":
    raise SystemExit(launch.unit_main("python -m experiments.atari", UNITS, LIMIT_S, END_S))
