#!/usr/bin/env bash
# Make this checkout ready to build and test: the Debian packages in scripts/apt-packages.txt (or in the lists
# given as arguments) and a Python environment in .venv/ with the project installed editable with the optional
# dependencies named by --extras (pyproject.toml; default every extra and the test tools, "all,test").
# Idempotent: a second run checks, prints one line, and installs nothing. .venv/.installed keeps pyproject.toml's
# digest and the extras installed; asking for extras not among them installs those beside them.
set -euo pipefail
cd "$(dirname "$0")/.."

# --packages-only: the Debian packages alone (make test builds and tests the firmware, which needs them, while the
# Python environment installs). The package lists to install: the arguments (e.g. scripts/apt-packages-figures.txt
# as well), else the one for building and testing.
# --extras LIST: the optional dependencies to install (comma-separated extras of pyproject.toml; make demo asks for
# its own, "demo", without the test tools and the stacks it does not use).
packages_only=false
extras=all,test
while [ $# -gt 0 ]; do
    case "$1" in
        --packages-only) packages_only=true; shift ;;
        --extras) extras=${2:?"bootstrap: --extras needs a comma-separated list of pyproject.toml's extras"}; shift 2 ;;
        *) break ;;
    esac
done
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
if $packages_only; then
    exit 0
fi

python=${PYTHON:-python3}
stamp=.venv/.installed
digest=$(sha256sum pyproject.toml | cut -d' ' -f1)
stamped_digest="" stamped_extras=""
if [ -f "$stamp" ]; then read -r stamped_digest stamped_extras < "$stamp" || true; fi
# the extras wanted: those asked for, with those already installed when pyproject.toml has not changed since
installed=""
if [ "$stamped_digest" = "$digest" ]; then
    installed=$stamped_extras
fi
wanted=$(printf '%s\n' ${installed//,/ } ${extras//,/ } | sort -u | paste -sd, -)
# "all" holds what "demo" holds: make demo after make test installs nothing
case ",$wanted," in *,all,*) wanted=$(printf '%s\n' ${wanted//,/ } | grep -vx demo | paste -sd, -) ;; esac
if [ ! -x .venv/bin/python ]; then
    echo "bootstrap: creating .venv with $($python --version)"
    "$python" -m venv .venv
fi
if [ "$installed" != "$wanted" ]; then
    echo "bootstrap: installing the project and its extras $wanted into .venv (about a minute the first time)"
    log=.venv/install.log
    # --no-compile: pip byte-compiles every module it installs (a third of the install's time, 54 against 37 s
    # here); Python compiles the few a command imports on first use instead, in a fraction of a second.
    if ! { .venv/bin/python -m pip install -q --upgrade pip \
           && .venv/bin/python -m pip install -q --no-compile -e ".[$wanted]"; } \
        >"$log" 2>&1; then
        cat "$log" >&2
        echo "bootstrap: pip failed (output above, also in $log)" >&2
        exit 1
    fi
    # Once per install: what the daemon's default model (builtin:converged) needs that does not ship with it,
    # so that a first `phantom daemon` or `make demo` starts in seconds: the model's kernels compiled ahead of
    # time, its 10-node mesh, its rest compliance and factorisation (cached per machine). Its response table
    # (volumes and shapes) ships with it: nothing to solve. Not fatal: without them the daemon compiles and
    # meshes on its first start.
    echo "bootstrap: preparing the daemon's default model (builtin:converged): compiling the kernels, meshing" \
        "it and factorising its stiffness (one to two minutes, once; its response table ships with it)"
    if ! { .venv/bin/python -m phantom.model.fem.kernels \
           && .venv/bin/phantom inverse --scene builtin:converged --volume-ml 30 --json; } >>"$log" 2>&1; then
        echo "bootstrap: warning: preparing the model failed (see $log); the daemon prepares it on first use"
    fi
    echo "$digest $wanted" > "$stamp"
fi
echo "bootstrap: ready (Debian packages present, .venv up to date)"
