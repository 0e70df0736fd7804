#!/usr/bin/env bash
# Make this checkout ready to build and test: the Debian packages in scripts/apt-packages.txt (or in the lists
# given as arguments) and a Python environment in .venv/ with the project installed editable with every extra
# (pyproject.toml).
# Idempotent: a second run checks, prints one line, and installs nothing.
set -euo pipefail
cd "$(dirname "$0")/.."

# The package lists to install: the arguments (e.g. scripts/apt-packages-figures.txt as well), else the one for
# building and testing.
lists=("${@:-scripts/apt-packages.txt}")
packages=$(sed -e 's/#.*//' -e '/^[[:space:]]*$/d' "${lists[@]}")
missing=""
for package in $packages; do
    dpkg-query -W -f='${Status}' "$package" 2>/dev/null | grep -q "install ok installed" || missing="$missing $package"
done
if [ -n "$missing" ]; then
    if [ "$(id -u)" -eq 0 ]; then
        as_root=""
    elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
        as_root="sudo"
    else
        echo "bootstrap: these Debian packages are missing:$missing" >&2
        echo "bootstrap: install them as root:  sudo apt-get install -y$missing" >&2
        exit 1
    fi
    echo "bootstrap: installing Debian packages:$missing"
    $as_root apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $as_root apt-get install -y -qq --no-install-recommends $missing >/dev/null
fi

python=${PYTHON:-python3}
stamp=.venv/.installed
wanted=$(sha256sum pyproject.toml | cut -d' ' -f1)
if [ ! -x .venv/bin/python ]; then
    echo "bootstrap: creating .venv with $($python --version)"
    "$python" -m venv .venv
fi
if [ "$(cat "$stamp" 2>/dev/null)" != "$wanted" ]; then
    echo "bootstrap: installing the project and every extra into .venv (one to two minutes the first time)"
    log=.venv/install.log
    if ! { .venv/bin/python -m pip install -q --upgrade pip && .venv/bin/python -m pip install -q -e ".[all,test]"; } \
        >"$log" 2>&1; then
        cat "$log" >&2
        echo "bootstrap: pip failed (output above, also in $log)" >&2
        exit 1
    fi
    # Once per install: compile the model's kernels ahead of time, then mesh and factorise the built-in scene,
    # so that a user's first `phantom forward` is a warm one (0.6 s instead of 10-15 s). Not fatal: without
    # them numba compiles the kernels and gmsh meshes on first use.
    echo "bootstrap: compiling the model's kernels and meshing the built-in phantom (about 15 s)"
    if ! { .venv/bin/python -m phantom.model.fem.kernels \
           && .venv/bin/phantom forward --scene builtin --pressures-kpa 1,1,1 --json; } >>"$log" 2>&1; then
        echo "bootstrap: warning: warming the model failed (see $log); it will compile and mesh on first use"
    fi
    # The daemon's default model answers from its response table: solve it now (once per machine, cached) rather
    # than in a first `phantom daemon` or a test's fixture, where it would count against a start-up deadline.
    echo "bootstrap: solving the calibrated model's response table, the daemon's default (1-5 minutes, once)"
    if ! .venv/bin/phantom inverse --scene builtin:calibrated --volume-ml 30 --json >>"$log" 2>&1; then
        echo "bootstrap: warning: building the response table failed (see $log); the daemon builds it on first use"
    fi
    echo "$wanted" > "$stamp"
fi
echo "bootstrap: ready (Debian packages present, .venv up to date)"
