#!/usr/bin/env bash
# Release wheel and wheelhouse: builds one abi3 wheel of gpmhe (every CPython >= 3.9) tagged
# manylinux2014 (glibc >= 2.17, x86_64), cross-linked with zig so that the tag holds whatever glibc
# this machine has; optionally puts it into a wheelhouse, a folder with the wheels of everything
# gpmhe and the chosen extras need, for machines with no network. Then it proves the wheel: it is
# installed off-line from a wheelhouse (pip install --no-index --find-links) into a fresh
# virtualenv whose PATH has no cargo or rustc, and the test suite runs against it.
#
#   bash scripts/build_wheel.sh                      # wheel in dist/, checked with python3
#   bash scripts/build_wheel.sh --wheelhouse wheelhouse --extras casadi,plot
#       # wheelhouse/: the wheel, and the wheels of numpy, SciPy, filterpy, CasADi, matplotlib and
#       # their dependencies; on the machine with no network:
#       #   pip install --no-index --find-links wheelhouse "gpmhe[casadi,plot]"
#   bash scripts/build_wheel.sh --python python3.9 --python python3.13   # checked with each
#   bash scripts/build_wheel.sh --wheelhouse wheelhouse --platform manylinux2014_x86_64
#   bash scripts/build_wheel.sh --no-check           # wheel (and wheelhouse) only
#   bash scripts/build_wheel.sh --tests "test_gp.py test_bank.py"   # the check runs these only
#
# The dependency wheels are downloaded (pip download --only-binary=:all:) by each --python
# interpreter (python3 by default), so they are for its Python version (give one --python per
# Python version of the target machines) and for this machine's platform: Linux x86_64 with this
# machine's glibc, which may be newer than the target machines'. --platform manylinux2014_x86_64
# asks pip for wheels that need glibc 2.17 only, as gpmhe's own wheel does (pip then takes an older
# release of a package whose newest wheels need more). The check installs gpmhe[test] (and the
# --extras) from the wheelhouse, a temporary one without --wheelhouse, so with the check the
# wheelhouse also holds the test extra's wheels; --no-check leaves them out. A relative DIR is
# taken from the directory the script is called from.
#
# Needs: python3 (3.9+), a Rust toolchain and the package registries; the check needs neither
# cargo nor rustc nor the network.
set -euo pipefail
caller=$PWD
cd "$(dirname "$0")/.."
root=$PWD
check=1
pythons=()
tests=.
wheelhouse=
extras=
platform=
while [ $# -gt 0 ]; do
    case "$1" in
        --no-check) check=0 ;;
        --python) shift; pythons+=("${1:?--python needs an interpreter}") ;;
        --tests) shift; tests="${1:?--tests needs test files}" ;;
        --wheelhouse) shift; wheelhouse="${1:?--wheelhouse needs a directory}" ;;
        --extras) shift; extras="${1:?--extras needs a comma-separated list, e.g. casadi,plot}" ;;
        --platform) shift; platform="${1:?--platform needs a platform tag, e.g. manylinux2014_x86_64}" ;;
        *) echo "unknown argument: $1 (see the comment at the top of $0)" >&2; exit 2 ;;
    esac
    shift
done
[ ${#pythons[@]} -gt 0 ] || pythons=(python3)

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

if [ -z "$wheelhouse" ] && [ "$check" = 1 ]; then
    wheelhouse="$work/wheelhouse"
fi
case ",$extras," in
    *,test,*) ;;
    *) [ "$check" = 0 ] || extras="${extras:+$extras,}test" ;;
esac
if [ -n "$wheelhouse" ]; then
    wheelhouse=$(cd "$caller" && mkdir -p "$wheelhouse" && cd "$wheelhouse" && pwd)
fi

echo "== build tools (maturin, zig) in a throw-away virtualenv"
python3 -m venv "$work/build"
"$work/build/bin/pip" install --quiet "maturin>=1.7,<2" "ziglang>=0.11"

echo "== maturin build --release --zig --compatibility manylinux2014"
rm -f dist/gpmhe-*.whl
# maturin finds zig through the ziglang package of the interpreter that runs it.
PATH="$work/build/bin:$PATH" "$work/build/bin/maturin" build --release --zig \
    --compatibility manylinux2014 --out dist
wheel=$(ls "$root"/dist/gpmhe-*-cp39-abi3-manylinux*_x86_64.whl)
echo "built $wheel"
[ -n "$wheelhouse" ] || exit 0

fill_wheelhouse() {  # $1: a virtualenv of the interpreter the dependency wheels are for
    echo "== wheelhouse $wheelhouse: gpmhe${extras:+[$extras]} for $("$1/bin/python" -c 'import sys; print("Python", sys.version.split()[0])')"
    # pip download copies the wheel given as a file into the wheelhouse, next to its dependencies.
    "$1/bin/pip" download --quiet --only-binary=:all: ${platform:+--platform "$platform"} \
        --dest "$wheelhouse" "$wheel${extras:+[$extras]}"
}

check_with() {  # $1: a fresh virtualenv; installs from the wheelhouse only, then runs the tests
    echo "== check with $1: install off-line from the wheelhouse, no Rust toolchain on PATH, run the tests"
    # The virtualenv and the system's directories only: no ~/.cargo/bin.
    local clean_path="$1/bin:/usr/local/bin:/usr/bin:/bin"
    if PATH="$clean_path" command -v cargo >/dev/null || PATH="$clean_path" command -v rustc >/dev/null; then
        echo "cargo or rustc is on the check's PATH ($clean_path): the check would prove nothing" >&2
        exit 1
    fi
    (
        export PATH="$clean_path" PIP_CACHE_DIR="$work/pip-cache"
        # No network for pip: no index, no configuration files (they could name one), and a proxy
        # that refuses every connection, so anything missing from the wheelhouse fails here.
        unset PIP_INDEX_URL PIP_EXTRA_INDEX_URL PIP_FIND_LINKS no_proxy NO_PROXY
        export PIP_NO_INDEX=1 PIP_CONFIG_FILE=/dev/null PIP_DISABLE_PIP_VERSION_CHECK=1
        export http_proxy=http://127.0.0.1:9 https_proxy=http://127.0.0.1:9
        export HTTP_PROXY=$http_proxy HTTPS_PROXY=$https_proxy ALL_PROXY=$http_proxy
        pip install --quiet --no-index --find-links "$wheelhouse" --only-binary=:all: "gpmhe[$extras]"
        cd "$root/tests"
        python -c "import gpmhe, sys; print('gpmhe', gpmhe.__version__, 'on Python', sys.version.split()[0], 'from', gpmhe.__file__)"
        # shellcheck disable=SC2086  # the files are separate words
        python -m pytest -q $tests
    )
}

rm -f "$wheelhouse"/gpmhe-*.whl  # an older build would be a second candidate for pip
for i in "${!pythons[@]}"; do
    py=$(command -v "${pythons[$i]}" || echo "${pythons[$i]}")
    venv="$work/venv-$i-$(basename "$py")"
    "$py" -m venv "$venv"
    fill_wheelhouse "$venv"
    [ "$check" = 0 ] || check_with "$venv"
done
if [ "$wheelhouse" != "$work/wheelhouse" ]; then
    echo "wheelhouse: $wheelhouse ($(ls "$wheelhouse" | wc -l) wheels, $(du -sh "$wheelhouse" | cut -f1))"
fi
[ "$check" = 0 ] || echo "wheel checked off-line with ${pythons[*]}: $wheel"
