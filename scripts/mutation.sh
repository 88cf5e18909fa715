#!/usr/bin/env bash
# Mutation testing (mutmut 3) of the pure-Python geometry: deformation.py, session.py, io/_volume.py and
# skeleton/_curve.py, each against its fast tests ([tool.mutmut] in pyproject.toml). Not part of the default test
# run; see docs/testing-mutation.md for the last figures and the survivors left on purpose.
#
#   scripts/mutation.sh                                        # every mutant (about 3 900: hours on one core)
#   scripts/mutation.sh 'napari_unwind.skeleton._curve.*'      # mutant-name globs: a module, a function ...
#   scripts/mutation.sh 'napari_unwind.session.*__mutmut_*0'   # ... or a sample (here one mutant in ten)
#
# Named sets (issue 19): MUTATION_SET=NAME mutates only that set's modules against only its tests
# ([tool.mutmut.sets.NAME] in pyproject.toml: atomic, editing, foldfree, services, volume, deformation,
# session), e.g.
#
#   MUTATION_SET=atomic scripts/mutation.sh 'napari_unwind.io._atomic.*__mutmut_*[05]'   # one mutant in five
#   MUTATION_SET=services scripts/mutation.sh 'unwind_services.*'
#
# mutmut reads only [tool.mutmut] and only puts mutants/ (or mutants/src) on sys.path, so for a set the script
# (a) writes the set's only_mutate and tests over [tool.mutmut] in the private worktree's pyproject.toml, and
# (b) copies services/unwind_services to ./unwind_services there, listed in source_paths beside napari_unwind: the
# service package (installed from services/, outside napari_unwind) is then mutated as `unwind_services.auth` ...
# and imported from mutants/, never from the shared work tree through the editable install.
#
# Environment: MUTATION_SET (above), MUTATION_JOBS (workers, default 1), MUTATION_KEEP=1 (keep the private worktree, with mutants/, to
# look at mutants afterwards: `cd <it> && mutmut show NAME` or `mutmut browse`), PYTHON (default .venv/bin/python).
# Needs the `mutation` extra: .venv/bin/uv pip install --python .venv/bin/python -e ".[test,mutation]".
#
# It runs in a private git worktree of HEAD, so edits in the work tree (yours or anyone's) neither disturb it nor
# get mutated: commit what you want tested. mutmut copies the package to mutants/ and puts that first on sys.path;
# it stops by itself if the tests import the package from anywhere else.
set -euo pipefail

root=$(git rev-parse --show-toplevel)
py=${PYTHON:-$root/.venv/bin/python}
mutmut=$(dirname "$py")/mutmut
if [ ! -x "$mutmut" ]; then
    echo "mutation.sh: $mutmut not found; install the 'mutation' extra (see the top of this script)" >&2
    exit 1
fi

wt=$(mktemp -d "${TMPDIR:-/tmp}/unwind-mutation.XXXXXX")
cleanup() {
    if [ "${MUTATION_KEEP:-0}" = 1 ]; then
        echo "mutation.sh: kept $wt (remove it with: git worktree remove --force $wt)"
    else
        git -C "$root" worktree remove --force "$wt" || true
    fi
}
trap cleanup EXIT
rmdir "$wt"
git -C "$root" worktree add --detach --quiet "$wt" HEAD
cd "$wt"

if [ -n "${MUTATION_SET:-}" ]; then
    cp -r services/unwind_services unwind_services
    MUTATION_SET=$MUTATION_SET "$py" - <<'PY'
import json
import os
import re
import tomllib
from pathlib import Path

name = os.environ["MUTATION_SET"]
p = Path("pyproject.toml")
text = p.read_text()
sets = tomllib.loads(text)["tool"]["mutmut"].get("sets", {})
if name not in sets:
    raise SystemExit(f"mutation.sh: no set {name!r} in [tool.mutmut.sets] (have: {', '.join(sets)})")
s = sets[name]
block = (f"[tool.mutmut]\n# MUTATION_SET={name}, written by scripts/mutation.sh\n"
         f'source_paths = ["napari_unwind", "unwind_services"]\n'
         f"only_mutate = {json.dumps(s['only_mutate'])}\n"
         f"pytest_add_cli_args_test_selection = {json.dumps(s['tests'])}\n"
         f'pytest_add_cli_args = ["-p", "no:cacheprovider"]\nprocess_isolation = "forkserver"\n\n')
# the whole [tool.mutmut] table with its sub-tables, up to the next table that is not one of them
new, n = re.subn(r"(?ms)^\[tool\.mutmut[].].*?(?=^\[(?!tool\.mutmut[].]))", lambda _: block, text, count=1)
assert n == 1, "mutation.sh: [tool.mutmut] not found"
p.write_text(new)
print(f"mutation.sh: set {name}: {s['only_mutate']} against {s['tests']}")
PY
fi

start=$(date +%s)
"$mutmut" run --max-children "${MUTATION_JOBS:-1}" "$@" > mutation.log 2>&1 || {
    status=$?
    tail -n 30 mutation.log | tr '\r' '\n' | tail -n 30 >&2
    echo "mutation.sh: mutmut run failed (exit $status); log: $wt/mutation.log" >&2
    MUTATION_KEEP=1
    exit "$status"
}
echo "mutation.sh: mutmut run took $(( $(date +%s) - start )) s"

"$py" - <<'PY'
import json
from collections import Counter
from pathlib import Path

from mutmut.stats import status_by_exit_code

caught = ("killed", "timeout", "segfault")
print(f"{'module':38} {'mutants':>7} {'checked':>7} {'killed':>6} {'timeout':>7} {'survived':>8} {'no test':>7} "
      f"{'kill rate':>9}")
survivors = []
for meta in sorted(Path("mutants").rglob("*.py.meta")):
    codes = json.loads(meta.read_text())["exit_code_by_key"]
    n = Counter(status_by_exit_code[c] for c in codes.values())
    checked = len(codes) - n["not checked"]
    killed = sum(n[s] for s in caught)
    reached = killed + n["survived"]
    rate = f"{100 * killed / reached:.1f} %" if reached else "-"
    name = str(meta.relative_to("mutants"))[: -len(".meta")]
    print(f"{name:38} {len(codes):7} {checked:7} {n['killed']:6} {n['timeout'] + n['segfault']:7} "
          f"{n['survived']:8} {n['no tests']:7} {rate:>9}")
    survivors += [k for k, c in codes.items() if status_by_exit_code[c] in ("survived", "no tests")]
print("kill rate = (killed + timeout) / (killed + timeout + survived); 'no test': no selected test reaches it")
print(f"\n{len(survivors)} surviving or untested mutants (see one with: mutmut show NAME):")
for k in survivors:
    print("  ", k)
PY
