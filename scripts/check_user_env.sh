#!/usr/bin/env bash
# Install nerfuser_ns the way a user does, into a nerfstudio environment they already have, and test it there.
#
# The "user environment" is a second virtual environment like the one nerfstudio's install guide builds:
# Python 3.10, torch 2.1.2 + torchvision 0.16.2 from PyPI (the default Linux wheels are CUDA builds; they run on
# CPU), numpy 1.x (what torch 2.1 was built against), then `pip install nerfstudio==1.1.5`. It is kept in
# ~/.cache/nerfuser_ns/userenv-py310-torch21 (override: NERFUSER_USERENV) and reused while the base environment's
# pins and Python are unchanged. Every run then installs this checkout into it as a user would
# (`pip install <repo>[dev]`: a real, non-editable install of a copy of the working tree), fails if pip replaced
# the user's torch, checks that
# `import cv2` works, and runs the registration and fused-model tests against the INSTALLED package (the tests
# are copied to a temporary folder, so the checkout is never on sys.path).
#
#   scripts/check_user_env.sh                      # build or reuse the environment, install, test
#   PYTEST_ARGS="-x" scripts/check_user_env.sh     # extra pytest arguments
#   TESTS="tests/registration/test_pipeline.py" scripts/check_user_env.sh
#
# Needs the package registry only while installing; the tests themselves run offline.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
TORCH_PINS=(torch==2.1.2 torchvision==0.16.2 "numpy<2")
NERFSTUDIO_PIN="nerfstudio==1.1.5"
REGISTRATION_TESTS="tests/registration/test_pipeline.py tests/registration/test_record.py tests/registration/test_refine.py
tests/registration/test_render_cache.py tests/registration/test_self_check.py tests/registration/test_sfm.py
tests/bench/test_ground_truth.py"
TESTS="${TESTS:-tests/test_runtime.py $(echo $REGISTRATION_TESTS) tests/test_model.py}"
VENV="${NERFUSER_USERENV:-$HOME/.cache/nerfuser_ns/userenv-py310-torch21}"
MARK="$VENV/.nerfuser-userenv-complete"
# The machine's own pip find-links carry a torch wheel of ours (cp311, CPU); a user has only PyPI.
export PIP_FIND_LINKS=" " PIP_DISABLE_PIP_VERSION_CHECK=1
say() { echo "check_user_env: $*" >&2; }

# --- Python 3.10 --------------------------------------------------------------------------------------------------
find_python() {
    local cand pyenv_310
    pyenv_310="$(ls -d "${PYENV_ROOT:-$HOME/.pyenv}"/versions/3.10*/bin/python3.10 2>/dev/null | sort -V | tail -1)"
    for cand in "${PYTHON:-}" "$pyenv_310" "$(command -v python3.10 || true)"; do
        [ -n "$cand" ] && [ -x "$cand" ] || continue
        # a pyenv shim exists even when 3.10 is not selected: ask the interpreter itself
        if "$cand" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 10))' 2>/dev/null; then
            echo "$cand"
            return 0
        fi
    done
    return 1
}
PY310="$(find_python)" || { say "no Python 3.10 (pyenv install 3.10, or set PYTHON=/path/to/python3.10)"; exit 1; }
# the base environment is keyed by what goes into it (like setup_env.sh's key of the lock file); RECIPE names the
# way it is built (bump it when the commands below change)
RECIPE="2: pip upgraded, setuptools as the venv ships it"
KEY="$(echo "$("$PY310" --version) ${TORCH_PINS[*]} $NERFSTUDIO_PIN $RECIPE" | sha256sum | cut -c1-12)"

# --- the user's environment (cached) ------------------------------------------------------------------------------
if [ ! -f "$MARK" ] || [ "$(cat "$MARK")" != "$KEY" ]; then
    say "creating $VENV with $("$PY310" --version) (first run: ~10 min and ~6 GB, torch's CUDA libraries)"
    rm -rf "$VENV"
    mkdir -p "$(dirname "$VENV")"
    "$PY310" -m venv "$VENV"
    # as nerfstudio's install guide: pip upgraded, nothing else (the venv's own setuptools keeps pkg_resources,
    # which torch 2.1's inductor imports; setuptools >= 82 has none: runtime.py then warns, stock path)
    "$VENV/bin/pip" install --quiet --upgrade pip
    "$VENV/bin/pip" install --quiet "${TORCH_PINS[@]}"
    "$VENV/bin/pip" install --quiet "$NERFSTUDIO_PIN"
    echo "$KEY" >"$MARK"
else
    say "reusing $VENV"
fi
PY="$VENV/bin/python"
versions() {
    "$PY" - <<'EOF'
import importlib.metadata as md
names = ["torch", "torchvision", "numpy", "nerfstudio", "pycolmap", "open3d", "viser", "nerfuser-ns"]
def v(n):
    try:
        return md.version(n)
    except md.PackageNotFoundError:
        return "-"
print(" ".join(f"{n}={v(n)}" for n in names))
EOF
}
"$VENV/bin/pip" uninstall --quiet --yes nerfuser-ns >/dev/null 2>&1 || true  # a previous run's install
BEFORE="$(versions)"
TORCH_BEFORE="$("$PY" -c 'import importlib.metadata as m; print(m.version("torch"))')"

# --- install the plugin as a user does ----------------------------------------------------------------------------
WORK="$(mktemp -d "${TMPDIR:-/tmp}/nerfuser-userenv.XXXXXX")"
trap 'rm -rf "$WORK"' EXIT
# One snapshot of the working tree (tracked and untracked, not ignored files), the package and its tests together:
# building in the checkout itself would leave build/ and *.egg-info there.
mkdir "$WORK/src" "$WORK/run"
(cd "$ROOT" && git ls-files -z --cached --others --exclude-standard -- pyproject.toml README.md 'LICENSE*' \
    nerfuser_ns method_configs tests | while IFS= read -r -d '' f; do
    if [ -e "$f" ]; then printf '%s\0' "$f"; fi
done | xargs -0 cp --parents -t "$WORK/src") || { say "could not copy the working tree"; exit 1; }
mv "$WORK/src/tests" "$WORK/run/tests"
cp "$WORK/src/pyproject.toml" "$WORK/run/"  # pytest's settings only; no package folder beside it
t0=$SECONDS
say "pip install <checkout>[dev] (non-editable)"
"$VENV/bin/pip" install --quiet "$WORK/src[dev]"
INSTALL_S=$((SECONDS - t0))
AFTER="$(versions)"
TORCH_AFTER="$("$PY" -c 'import importlib.metadata as m; print(m.version("torch"))')"
say "before: $BEFORE"
say "after:  $AFTER"
if [ "$TORCH_BEFORE" != "$TORCH_AFTER" ]; then
    say "FAIL: pip replaced the user's torch ($TORCH_BEFORE -> $TORCH_AFTER)"
    exit 1
fi
# pip check fails on conflicts and on its own errors (pip 26 cannot parse gtsam 4.2's wheel tag
# cp310-cp310-none-manylinux2014_x86_64 and stops): say which
if ! PIP_CHECK="$("$VENV/bin/pip" check 2>&1)"; then
    if grep -q '^Traceback' <<<"$PIP_CHECK"; then
        say "warning: pip check could not run: $(tail -n 1 <<<"$PIP_CHECK")"
    else
        echo "$PIP_CHECK" >&2
        say "warning: pip check reports conflicts (above)"
    fi
fi

# --- imports ------------------------------------------------------------------------------------------------------
cd "$WORK"  # never the checkout: the installed package must be the one imported
CV2="$("$PY" -c 'import cv2; print(cv2.__version__)' 2>&1 | tail -1)" && CV2_OK=yes || CV2_OK=no
CV2_DISTS="$("$VENV/bin/pip" list 2>/dev/null | grep -i '^opencv' | tr -s ' ' '=' | tr '\n' ' ' || true)"
say "import cv2: $CV2_OK ($CV2); distributions shipping cv2: $CV2_DISTS"
"$PY" - "$VENV" <<'EOF'
import sys
from pathlib import Path

import torch

import nerfuser_ns
from nerfuser_ns import runtime

where = Path(nerfuser_ns.__file__).resolve()
assert Path(sys.argv[1]).resolve() in where.parents, f"nerfuser_ns imported from {where}, not the environment"
runtime.install()
print(f"check_user_env: nerfuser_ns from {where.parent}; torch {torch.__version__}, cuda build {torch.version.cuda}, "
      f"torch.compile usable: {runtime._compile_unusable_reason() or 'yes'}", file=sys.stderr)
EOF

# --- tests, once, against the installed package -------------------------------------------------------------------
cd "$WORK/run"
say "pytest $TESTS ${PYTEST_ARGS:-}"
t0=$SECONDS
set +e
# shellcheck disable=SC2086
"$PY" -m pytest -q -p no:cacheprovider $TESTS ${PYTEST_ARGS:-} 2>&1 | tee "$WORK/pytest.log"
RC=${PIPESTATUS[0]}
set -e
TEST_S=$((SECONDS - t0))
RESULT="$(grep -E '[0-9]+ (passed|failed|errors?)\b' "$WORK/pytest.log" | tail -1 | tr -d '=' | sed 's/^ *//')"

echo
echo "=== nerfuser_ns in a user's nerfstudio environment ($VENV)"
echo "python:      $("$PY" --version 2>&1 | cut -d' ' -f2)"
echo "torch:       $TORCH_BEFORE before, $TORCH_AFTER after the plugin install (unchanged)"
echo "versions:    $AFTER"
echo "import cv2:  $CV2_OK ($CV2; $CV2_DISTS)"
echo "install:     ${INSTALL_S}s"
echo "tests:       ${RESULT:-no pytest summary} (exit $RC, ${TEST_S}s): $TESTS"
[ "$CV2_OK" = yes ] || { say "FAIL: import cv2"; exit 1; }
exit "$RC"
