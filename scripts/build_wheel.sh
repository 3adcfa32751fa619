#!/usr/bin/env bash
# Release wheel: builds one abi3 wheel of gpmhe (every CPython >= 3.9) tagged manylinux2014
# (glibc >= 2.17, x86_64), cross-linked with zig so that the tag holds whatever glibc this machine
# has, then proves it: the wheel is installed into a fresh virtualenv whose PATH has no cargo or
# rustc, and the test suite runs against it.
#
#   bash scripts/build_wheel.sh                      # wheel in dist/, checked with python3
#   bash scripts/build_wheel.sh --python python3.9 --python python3.13   # checked with each
#   bash scripts/build_wheel.sh --no-check           # wheel only
#   bash scripts/build_wheel.sh --tests "test_gp.py test_bank.py"   # the check runs these only
#
# Needs: python3 (3.9+) and a Rust toolchain to build; the check needs neither cargo nor rustc.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$PWD
check=1
pythons=()
tests=.
while [ $# -gt 0 ]; do
    case "$1" in
        --no-check) check=0 ;;
        --python) shift; pythons+=("${1:?--python needs an interpreter}") ;;
        --tests) shift; tests="${1:?--tests needs test files}" ;;
        *) echo "unknown argument: $1 (see the comment at the top of $0)" >&2; exit 2 ;;
    esac
    shift
done
[ ${#pythons[@]} -gt 0 ] || pythons=(python3)

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

echo "== build tools (maturin, zig) in a throw-away virtualenv"
python3 -m venv "$work/build"
"$work/build/bin/pip" install --quiet "maturin>=1.7,<2" "ziglang>=0.11"

echo "== maturin build --release --zig --compatibility manylinux2014"
rm -f dist/gpmhe-*.whl
# maturin finds zig through the ziglang package of the interpreter that runs it.
PATH="$work/build/bin:$PATH" "$work/build/bin/maturin" build --release --zig \
    --compatibility manylinux2014 --out dist
wheel=$(ls dist/gpmhe-*-cp39-abi3-manylinux*_x86_64.whl)
echo "built $wheel"
[ "$check" = 1 ] || exit 0

check_with() {  # $1: the interpreter that creates the check's virtualenv
    local venv="$work/check-$(basename "$1")"
    echo "== check with $1: install the wheel with no Rust toolchain on PATH, run the tests"
    "$1" -m venv "$venv"
    # The virtualenv and the system's directories only: no ~/.cargo/bin.
    local clean_path="$venv/bin:/usr/local/bin:/usr/bin:/bin"
    if PATH="$clean_path" command -v cargo >/dev/null || PATH="$clean_path" command -v rustc >/dev/null; then
        echo "cargo or rustc is on the check's PATH ($clean_path): the check would prove nothing" >&2
        exit 1
    fi
    (
        export PATH="$clean_path" PIP_CACHE_DIR="$work/pip-cache"
        pip install --quiet --only-binary=gpmhe "$wheel[test]"
        cd "$root/tests"
        python -c "import gpmhe, sys; print('gpmhe', gpmhe.__version__, 'on Python', sys.version.split()[0], 'from', gpmhe.__file__)"
        # shellcheck disable=SC2086  # the files are separate words
        python -m pytest -q $tests
    )
}
for py in "${pythons[@]}"; do
    check_with "$(command -v "$py" || echo "$py")"
done
echo "wheel checked with ${pythons[*]}: $wheel"
