#!/usr/bin/env bash
# Prepare, HERE (a machine with network access), what bench/gpu_check.sh needs on a lent GPU machine.
#
#   bench/gpu_carry.sh            -> .gpu/site.zip (ignored by git), carried with the working tree
#
# The lent machine has Python 3.12 and torch with CUDA, and no network: Mitsuba, Dr.Jit and the
# project's dependencies its image lacks travel as one zip of a site-packages folder, which
# gpu_check.sh unpacks into /tmp there. The device tool carries at most 64 MiB with the working
# tree, and Mitsuba's cp312 wheel alone is 62.6 MB: its variants other than cuda_ad_rgb and
# scalar_rgb (about 1.3 MB each, compressed), its headers, stubs and build files are left out.
# The downloads are cached in $NDRF_GPU_CACHE (default ~/.cache/ndrf-gpu), outside the tree.
#
# Carried beside Mitsuba and Dr.Jit (the versions of pyproject.toml / this checkout's .venv):
# pydantic (+ pydantic-core, annotated-types, typing-inspection, typing-extensions),
# pydantic-settings (+ python-dotenv), fastapi (+ starlette, opentelemetry-api), defusedxml, OpenEXR.
# Found by trying the zip with a Python 3.12 that holds only the image's packages. Assumed present in
# the device image (docs of the device tool, KINDS.md): numpy, torch, pillow, click, rich, httpx,
# anyio, annotated-doc, prometheus-client, pytest; redis and obstore are not needed by the check.
set -euo pipefail
cd "$(dirname "$0")/.."

PIP=${PIP:-.venv/bin/pip}
CACHE=${NDRF_GPU_CACHE:-$HOME/.cache/ndrf-gpu}
KEEP_VARIANTS=${KEEP_VARIANTS:-cuda_ad_rgb scalar_rgb}   # add llvm_ad_rgb to try the zip on a CPU
LIMIT=$((64 * 1024 * 1024))
PACKAGES=(
  mitsuba==3.9.1 drjit==1.5.0
  pydantic==2.14.4 pydantic-core==2.50.5 annotated-types==0.8.0 typing-inspection==0.4.5 typing-extensions==4.16.0
  pydantic-settings==2.16.3 python-dotenv==1.2.4 fastapi==0.165.0 starlette==1.10.0 defusedxml==0.7.1
  OpenEXR==3.5.3 opentelemetry-api==1.45.2
)

mkdir -p "$CACHE" .gpu
# shellcheck disable=SC2086
$PIP download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
  --platform manylinux2014_x86_64 -d "$CACHE" "${PACKAGES[@]}"

KEEP_VARIANTS="$KEEP_VARIANTS" CACHE="$CACHE" python3 - "${PACKAGES[@]}" <<'EOF'
import os, re, sys, zipfile
from pathlib import Path

cache, keep = Path(os.environ["CACHE"]), set(os.environ["KEEP_VARIANTS"].split())
variant = re.compile(r"^mitsuba/((?:scalar|llvm|cuda)_(?:ad_)?\w+?)\.cpython-[^/]*\.so$")
dropped_dirs = ("mitsuba/include/", "mitsuba/cmake/", "mitsuba/pkgconfig/", "mitsuba/mitsuba_stubs/",
                "drjit/include/", "drjit/cmake/", "share/")
wanted = {re.split("==", p)[0].lower().replace("-", "_") for p in sys.argv[1:]}
wheels = [w for w in sorted(cache.glob("*.whl")) if w.name.split("-")[0].lower() in wanted
          and ("cp312" in w.name or "py3-none" in w.name or "py2.py3" in w.name)]
kept = dropped = 0
with zipfile.ZipFile(".gpu/site.zip", "w", zipfile.ZIP_DEFLATED, compresslevel=9) as out:
    for wheel in wheels:
        with zipfile.ZipFile(wheel) as z:
            for info in z.infolist():
                name = info.filename
                m = variant.match(name)
                if (m and m.group(1) not in keep) or name.startswith(dropped_dirs) or name.endswith(".pyi"):
                    dropped += info.file_size
                    continue
                kept += info.file_size
                if name.endswith((".so", ".zip")) or ".so." in name:      # already compressed or binary
                    out.writestr(info, z.read(name), compress_type=zipfile.ZIP_DEFLATED, compresslevel=6)
                else:
                    out.writestr(info, z.read(name))
    # the checkout runs uninstalled there: the metadata the API reads its version from (api/app.py)
    version = re.search(r'^version = "([^"]+)"', Path("pyproject.toml").read_text(), re.M).group(1)
    out.writestr(f"ndrf-{version}.dist-info/METADATA", f"Metadata-Version: 2.1\nName: ndrf\nVersion: {version}\n")
print(f"{len(wheels)} wheels -> .gpu/site.zip: {kept / 2**20:.1f} MiB unpacked kept, {dropped / 2**20:.1f} MiB left out")
EOF

zip_bytes=$(stat -c %s .gpu/site.zip)
tree_bytes=$(git ls-files -z --cached --others --exclude-standard | xargs -0 stat -c %s 2>/dev/null | awk '{s += $1} END {print s + 0}')
total=$((zip_bytes + tree_bytes))
awk -v z="$zip_bytes" -v t="$tree_bytes" 'BEGIN { printf ".gpu/site.zip %.1f MiB + working tree %.1f MiB = %.1f MiB of the 64 MiB a device call carries\n", z / 1048576, t / 1048576, (z + t) / 1048576 }'
if [ "$total" -gt "$LIMIT" ]; then
  echo "too large for one device call: leave more out (KEEP_VARIANTS, plugins)" >&2
  exit 1
fi
