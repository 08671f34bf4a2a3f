"""python -m experiments.offpolicy {list,run}: the off-policy experiment's GPU units (experiments/offpolicy/units.py)."""

from experiments import launch
from experiments.offpolicy.units import END_S, LIMIT_S, UNITS

if __name__ == "__main__":
    raise SystemExit(launch.unit_main("python -m experiments.offpolicy", UNITS, LIMIT_S, END_S))
