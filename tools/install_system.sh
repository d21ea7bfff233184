#!/usr/bin/env bash
# Install the Debian packages rodsnes needs, only those that are missing.
set -euo pipefail
PKGS="python3-petsc4py petsc-dev python3-mpi4py python3-h5py-mpi python3-meshio python3-scipy
python3-matplotlib python3-pytest python3-pytest-xdist python3-venv libmetis-dev openmpi-bin gcc
libopenblas0-serial"
missing=""
for p in $PKGS; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "ok installed" || missing="$missing $p"
done
if [ -z "$missing" ]; then exit 0; fi
echo "rodsnes: installing Debian packages:$missing"
SUDO=""
if [ "$(id -u)" != 0 ]; then
  command -v sudo >/dev/null || { echo "rodsnes: need root (or sudo) to install:$missing" >&2; exit 1; }
  SUDO=sudo
fi
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends $missing
