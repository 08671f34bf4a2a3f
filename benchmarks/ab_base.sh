#!/usr/bin/env bash
# runs/ab-base/: the cdjax package and the benchmark modules as they are at git revision REV, for the `ab` unit of
# benchmarks/compile_units.sh (an A/B of the working tree against REV in one lease). Run here, from the repository
# root; then carry runs/ab-base (about 1 MB) with .whl-site:
#
#   bash benchmarks/ab_base.sh REV
set -eu
rev=${1:?usage: bash benchmarks/ab_base.sh REV}
git rev-parse --verify -q "$rev^{commit}" > /dev/null || { echo "not a revision: $rev" >&2; exit 2; }
rm -rf runs/ab-base && mkdir -p runs/ab-base
git archive "$rev" cdjax pyproject.toml $(git ls-tree --name-only "$rev" benchmarks/ | grep '\.py$') \
  | tar -x -C runs/ab-base
git rev-parse --short "$rev" > runs/ab-base/REVISION
echo "runs/ab-base: revision $(cat runs/ab-base/REVISION), $(du -sh runs/ab-base | cut -f1)"
