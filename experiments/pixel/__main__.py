"""python -m experiments.pixel {list,run}: the pixel experiment's GPU units (experiments/pixel/units.py)."""

from experiments import launch
from experiments.pixel.units import END_S, LIMIT_S, UNITS

if __name__ == "__main__":
    raise SystemExit(launch.unit_main("python -m experiments.pixel", UNITS, LIMIT_S, END_S))
