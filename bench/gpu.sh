#!/usr/bin/env bash
# The GPU run of the benchmarks on a machine that reaches no package index (docs/developing.md,
# "A GPU run").
#
#   bench/gpu.sh bundle [THESIS]   here: packs bench/.gpu/ (ignored), the one path to carry:
#                                  the wheels' contents for CPython $PY (default 3.12), mitsuba
#                                  with its RGB variants only, xz-compressed (the carry limit is
#                                  64 MiB); the gRPC stubs; the thesis's scenes from THESIS
#                                  (default /work/thesis; Tables 2 and 4's folders), which the
#                                  repository may not hold.
#   bench/gpu.sh device OUT [ARGS]  there: installs bench/.gpu/ into a new venv without any
#                                  index, and runs `bench/run.py --gpu --out OUT/gpu ARGS`.
#   bench/gpu.sh splice DIR [ARGS] here: bench/run.py --splice on what came back (DIR: OUT, which
#                                  holds OUT/gpu packed as gpu.tar.gz, or an unpacked OUT/gpu);
#                                  ARGS: --add-seeds to add real_scenes' seeds to the run before.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
bundle=$root/bench/.gpu
py=${PY:-3.12}
python=${PYTHON:-python3}
# The daemon's and clients' dependencies at the versions tested here (pyproject.toml's ranges).
wheels=(mitsuba==3.9.1 drjit==1.5.0 grpcio==1.85.3 protobuf==7.36.2 numpy==2.4.6 click==8.5.1
        tqdm==4.70.1 tabulate==0.10.0 grpcio-health-checking==1.85.1 grpcio-reflection==1.85.1
        grpcio-status==1.85.3 googleapis-common-protos==1.76.0 cholespy==2.2.0
        prometheus_client==0.26.0 typing_extensions==4.16.0)

case ${1:-} in
bundle)
  thesis=${2:-/work/thesis}
  tmp=$(mktemp -d)
  trap 'rm -rf "$tmp"' EXIT
  "$python" -m pip download -q --no-deps --only-binary=:all: --python-version "$py" \
    --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
    --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d "$tmp/whl" "${wheels[@]}"
  mkdir -p "$tmp/site"
  for w in "$tmp"/whl/*.whl; do (cd "$tmp/site" && "$python" -m zipfile -e "$w" .); done
  # Only the RGB variants (scalar_rgb, llvm_ad_rgb, cuda_ad_rgb): the rest is half the size.
  rm -f "$tmp"/site/mitsuba/*_mono*.so "$tmp"/site/mitsuba/*_spectral*.so \
        "$tmp"/site/mitsuba/*polarized*.so
  rm -rf "$bundle" && mkdir -p "$bundle"
  tar -cJf "$bundle/site.tar.xz" -C "$tmp/site" .
  tar -cf "$bundle/stubs.tar" -C "$root/proto/matopt_api/v1" $(cd "$root/proto/matopt_api/v1" && ls ./*_pb2*.py)
  # The folders of the scenes bench/ reads (real_scenes' and calibration's tables), not all
  # of the thesis's (64 MiB would not hold them beside the wheels).
  m=scenes/material-preview
  tar -cJf "$bundle/thesis.tar.xz" -C "$thesis" $m/translucent-principled-bsdf \
    $m/translucent-participating-media $m/meshes
  echo "$py" > "$bundle/python-version"
  # The tree travels without git: the commit as of now (build the bundle after the last commit)
  commit=$(git -C "$root" rev-parse --short HEAD)
  if git -C "$root" status --porcelain -- daemon proto bench | grep -q .; then
    commit="$commit, daemon/, proto/ or bench/ modified"
  fi
  echo "$commit (when its bundle was built)" > "$bundle/commit"
  du -ch "$bundle"/*
  ;;
device)
  out=${2:?give the output folder}; shift 2
  venv=${VENV:-/tmp/matopt-gpu-venv}
  rm -rf "$venv" /tmp/matopt-thesis && mkdir -p /tmp/matopt-thesis "$out/gpu"
  want=python$(cat "$bundle/python-version")
  command -v "$want" >/dev/null || want=python3
  export PYTHONPATH=$root/proto:$root/clients:$root/daemon
  # One kernel cache for every case's daemon: the machine starts cold, and each case's warm-up
  # would otherwise compile the same kernels again on the loan's time.
  export DRJIT_CACHE_DIR=${DRJIT_CACHE_DIR:-/tmp/matopt-kernel-cache}
  export MATOPT_BENCH_COMMIT=$(cat "$bundle/commit" 2>/dev/null || echo unknown)
  if "$want" -m venv --without-pip "$venv"; then
    python=$venv/bin/python
    site=$("$python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
  else  # no venv module: the same files on PYTHONPATH, which the daemons inherit
    python=$want site=$venv/site
    mkdir -p "$site" && export PYTHONPATH=$PYTHONPATH:$site
  fi
  tar -xJf "$bundle/site.tar.xz" -C "$site" &
  tar -xf "$bundle/stubs.tar" -C "$root/proto/matopt_api/v1"
  tar -xJf "$bundle/thesis.tar.xz" -C /tmp/matopt-thesis
  (nvidia-smi || echo "no nvidia-smi") > "$out/gpu/nvidia-smi.txt" 2>&1
  wait
  cd "$root"
  "$python" -c 'import mitsuba, drjit, grpc, matoptd; print("mitsuba", mitsuba.__version__)'
  # The device tool brings back 8 files at most, none below two folders: one archive of the
  # run, packed even when the run fails or is stopped short of the command's own limit.
  rc=0
  timeout "${GPU_SECONDS:-530}" "$python" bench/run.py --gpu --out "$out/gpu" \
    --thesis-repo /tmp/matopt-thesis "$@" || rc=$?
  tar -czf "$out/gpu.tar.gz" -C "$out" gpu && rm -rf "$out/gpu"
  exit $rc
  ;;
splice)
  back=${2:?give the folder that came back}; shift 2
  cd "$root"
  export PYTHONPATH=$root/proto:$root/clients:$root/daemon
  [ -z "${PYTHON:-}" ] && [ -x .venv/bin/python ] && python=.venv/bin/python
  if [ -f "$back/gpu.tar.gz" ]; then
    tmp=$(mktemp -d)
    trap 'rm -rf "$tmp"' EXIT
    tar -xzf "$back/gpu.tar.gz" -C "$tmp" && back=$tmp/gpu
  fi
  "$python" bench/run.py --splice "$back" "$@"
  ;;
*)
  sed -n '2,15p' "$0" | sed 's/^# \{0,1\}//'
  exit 2
  ;;
esac
