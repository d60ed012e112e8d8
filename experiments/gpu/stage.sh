#!/usr/bin/env bash
# Fills .gpu-stage/ (ignored through .git/info/exclude) with what the device script gpu_comparison.sh
# (experiments/gpu/gpu_comparison.sh) needs and a lent GPU machine lacks: it has no package registry,
# and its image has torch, torchvision, torchmetrics, tensorboard, imageio, opencv, scipy,
# scikit-learn, matplotlib, tqdm, pyyaml, rich, jaxtyping, ninja, setuptools and pytest (Python
# 3.12), but not the packages below. Run it here, from the repository root:
#
#     bash experiments/gpu/stage.sh
#
# It needs pip (PyPI), the scene at $BEER and three git mirrors that the session's `fetch` makes
# (it says which are missing). The folder travels with the working tree when a device `run`
# names it in `carry`; the two together must stay under the 64 MiB a call carries, and this
# script fails above $LIMIT_MIB (60) so that the tree can still grow a little.
#
# What goes in, and why:
#   wheels/         CPython 3.12 manylinux x86-64 wheels, installed there with
#                   `pip install --no-index --no-deps --target`:
#                   - pycolmap (the official bindings): our COLMAP reader. 4.2.1, the version
#                     installed here, is a 38 MB wheel; when the total would pass the limit it is
#                     4.0.4 (27 MB), the oldest release the data tests pass on (pyproject.toml).
#                     The checkout's own shared/ travels too (10 MB of scenes when this was
#                     written), which leaves no room for 4.2.1;
#                   - tyro and what it imports (docstring-parser, typeguard): our CLIs and
#                     simple_trainer's;
#                   - plyfile: our PLY export (exploregs_plugin/io/ply.py);
#                   - viser, msgspec, websockets: `import viser` in simple_trainer.py,
#                     gsplat_viewer.py and nerfview, at module level, although the runs pass
#                     --disable_viewer; viser's trimesh is imported lazily and left out;
#                   - nerfview 0.1.3 (the PyPI release that contains the commit gsplat v1.5.3's
#                     examples/requirements.txt pins, 4538024) and splines, which it imports.
#   gsplat-1.5.3.tar.gz   gsplat's sdist: the same gsplat/ tree as the v1.5.3 tag (checked
#                   below) plus the glm headers of its git submodule, which its CUDA sources
#                   include. Repacked without that submodule's doc/ and test/ folders (18 MB of
#                   manuals and images, 0.8 MB of tests that no build reads): 1 MB instead of
#                   the 4.7 MB of PyPI's sdist or 6.5 MB of its wheel. There it is installed with BUILD_NO_CUDA=1
#                   (a pure package with its CUDA sources, as PyPI's wheel) and compiles on first
#                   use (about 75 s with MAX_JOBS=16 TORCH_CUDA_ARCH_LIST=9.0), the way every
#                   earlier GPU figure in docs/gpu.md was made.
#   gsplat-examples/   from the v1.5.3 tag: simple_trainer.py and what it imports beside it
#                   (datasets/colmap.py, normalize.py, traj.py, utils.py, gsplat_viewer.py).
#                   lib_bilagrid.py (and its tensorly) is imported only with --use_bilateral_grid,
#                   fused_bilagrid only with --use_fused_bilagrid, plas/torchpq only with
#                   --compression png: none of them is used, so none is carried.
#   fused-ssim/     source of fused-ssim at the commit that file pins (328dc98; no release on
#                   PyPI): simple_trainer imports `from fused_ssim import fused_ssim` at module
#                   level and uses it for its loss; it is a CUDA extension, built there.
#   st-shim/        a folder put first on PYTHONPATH for simple_trainer's runs only:
#                   - pycolmap/: the pure-Python fork (rmbrualla/pycolmap at cc7ea4b, the commit
#                     gsplat's examples pin, with its NumPy 2 fix: below) with `SceneManager`,
#                     which datasets/colmap.py imports. It has the same import name as the official bindings that our
#                     package uses, so it cannot sit in the shared wheels folder: first on the path
#                     of the simple_trainer process, it shadows the official one there and nowhere
#                     else. That process never needs the official one: the launcher
#                     exploregs_plugin.integrations.simple_trainer imports only torch, gsplat and
#                     our strategies (checked: importing it loads no pycolmap).
#                   - zstandard/: a stand-in. viser 1.1.1 imports zstandard at module level but
#                     calls it only to compress messages for a connected browser; with
#                     --disable_viewer no server starts, so nothing calls it. The real wheel is
#                     5.5 MB, which would push this folder over its limit; the stand-in raises
#                     if anything does call it.
#   beer/           a copy of $BEER (../shared does not travel).
set -euo pipefail
cd "$(git rev-parse --show-toplevel)"

STAGE=.gpu-stage
LIMIT_MIB=${LIMIT_MIB:-60}
BEER=${BEER:-../shared/scenes/beer}
MIRRORS=${MIRRORS:-/work/.mirror}
GSPLAT_GIT=${GSPLAT_GIT:-$MIRRORS/nerfstudio-project+gsplat/repo}
FORK_GIT=${FORK_GIT:-$MIRRORS/rmbrualla+pycolmap/repo}
FUSED_GIT=${FUSED_GIT:-$MIRRORS/rahul-goel+fused-ssim/repo}
GSPLAT_TAG=v1.5.3
# the mirrors are read only: no automatic gc or maintenance in them
git() { command git -c gc.auto=0 -c maintenance.auto=false "$@"; }
# the versions installed on the development machine, where the CPU tests pass with them
WHEELS=(tyro==1.0.17 docstring-parser==0.18.0 typeguard==4.6.1 plyfile==1.1.5
        viser==1.1.1 msgspec==0.22.0 websockets==16.1.1 nerfview==0.1.3 splines==0.3.3)
PYCOLMAP=(4.2.1 4.0.4)  # preferred, then the one that fits (see above)

missing=()
for repo in "$GSPLAT_GIT:nerfstudio-project/gsplat" "$FORK_GIT:rmbrualla/pycolmap" "$FUSED_GIT:rahul-goel/fused-ssim"; do
    git -C "${repo%%:*}" rev-parse --git-dir >/dev/null 2>&1 || missing+=("github:${repo#*:}")
done
if ((${#missing[@]})); then
    echo "stage.sh: no git mirror of ${missing[*]}: fetch each (the session's fetch tool) and run again" >&2
    exit 2
fi
[[ -f $BEER/sparse/0/points3D.bin ]] || { echo "stage.sh: $BEER is not the beer scene (no sparse/0/points3D.bin)" >&2; exit 2; }

grep -qxF "/$STAGE/" .git/info/exclude 2>/dev/null || echo "/$STAGE/" >>.git/info/exclude
chmod -R u+w "$STAGE" 2>/dev/null || true
rm -rf "$STAGE"
mkdir -p "$STAGE"/{wheels,gsplat-examples,fused-ssim,st-shim/zstandard}
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

# the commits gsplat's examples pin: read from the tag, so a different tag cannot pass unnoticed
reqs=$(git -C "$GSPLAT_GIT" show "$GSPLAT_TAG:examples/requirements.txt")
fork_commit=$(sed -n 's|^git+https://github.com/rmbrualla/pycolmap@\([0-9a-f]*\).*|\1|p' <<<"$reqs")
fused_commit=$(sed -n 's|^git+https://github.com/rahul-goel/fused-ssim@\([0-9a-f]*\).*|\1|p' <<<"$reqs")
[[ $fork_commit && $fused_commit ]] || { echo "stage.sh: $GSPLAT_TAG's examples/requirements.txt pins no pycolmap/fused-ssim commit" >&2; exit 1; }

download_wheels() {  # into $1
    nice -n 19 python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
        --platform manylinux2014_x86_64 --platform manylinux1_x86_64 --platform manylinux_2_5_x86_64 \
        -d "$@"
}
echo "== wheels (CPython 3.12, manylinux x86-64)"
download_wheels "$STAGE/wheels" "${WHEELS[@]}" "pycolmap==${PYCOLMAP[0]}"
n=$(ls "$STAGE"/wheels/*.whl | wc -l)
((n == ${#WHEELS[@]} + 1)) || { echo "stage.sh: $n wheels for $((${#WHEELS[@]} + 1)) packages" >&2; exit 1; }

echo "== gsplat 1.5.3 sdist"
# pip reads an sdist's metadata by running its setup.py, which imports torch unless BUILD_NO_CUDA=1
BUILD_NO_CUDA=1 nice -n 19 python3 -m pip download -q --no-deps --no-binary :all: --no-build-isolation \
    -d "$tmp" gsplat==1.5.3
mv "$tmp/gsplat-1.5.3.tar.gz" "$STAGE/"
mkdir -p "$tmp/sdist" "$tmp/tag/gsplat"
tar -xzf "$STAGE/gsplat-1.5.3.tar.gz" -C "$tmp/sdist"
git -C "$GSPLAT_GIT" archive "$GSPLAT_TAG:gsplat" | tar -x -C "$tmp/tag/gsplat"
# the sdist is the tag's gsplat/ (every file, byte for byte) plus the glm submodule's headers
diff -r --exclude=third_party "$tmp/tag/gsplat" "$tmp/sdist/gsplat-1.5.3/gsplat" \
    || { echo "stage.sh: the sdist's gsplat/ differs from the $GSPLAT_TAG tag" >&2; exit 1; }
csrc=$tmp/sdist/gsplat-1.5.3/gsplat/cuda/csrc
n_cu=$(ls "$csrc"/*.cu | wc -l)
[[ -f $csrc/third_party/glm/glm/glm.hpp && -f $tmp/sdist/gsplat-1.5.3/gsplat/cuda/ext.cpp ]] && ((n_cu > 0)) \
    || { echo "stage.sh: the sdist lacks its CUDA sources or the glm headers" >&2; exit 1; }
echo "   same gsplat/ as $GSPLAT_TAG; $n_cu .cu files, $(find "$csrc/third_party/glm/glm" -type f | wc -l) glm headers"
rm -rf "$csrc/third_party/glm/doc" "$csrc/third_party/glm/test"
tar --sort=name --owner=0 --group=0 -czf "$STAGE/gsplat-1.5.3.tar.gz" -C "$tmp/sdist" gsplat-1.5.3

echo "== simple_trainer.py and what it imports beside it ($GSPLAT_TAG)"
git -C "$GSPLAT_GIT" archive "$GSPLAT_TAG:examples" simple_trainer.py gsplat_viewer.py utils.py \
    datasets/colmap.py datasets/normalize.py datasets/traj.py | tar -x -C "$STAGE/gsplat-examples"

echo "== fused-ssim at $fused_commit"
git -C "$FUSED_GIT" archive "$fused_commit" setup.py ext.cpp ssim.cu ssim.h fused_ssim LICENSE \
    | tar -x -C "$STAGE/fused-ssim"

echo "== pycolmap fork (SceneManager) at $fork_commit, for simple_trainer's path only"
git -C "$FORK_GIT" archive "$fork_commit" pycolmap LICENSE.txt | tar -x -C "$STAGE/st-shim"
mv "$STAGE/st-shim/LICENSE.txt" "$STAGE/st-shim/pycolmap/"
# NumPy 2 (the device has 2.5) refuses np.uint64(-1), which this commit evaluates at import
# (OverflowError); the v1.5.3 tag asks for numpy<2. The fork's fix (its pull request 7, the
# commit gsplat's examples moved to later) writes the same value as 2**64 - 1.
sed -i 's/INVALID_POINT3D = np\.uint64(-1)$/INVALID_POINT3D = np.uint64(2**64 - 1)/' "$STAGE/st-shim/pycolmap/scene_manager.py"
grep -q 'INVALID_POINT3D = np.uint64(2\*\*64 - 1)$' "$STAGE/st-shim/pycolmap/scene_manager.py" \
    || { echo "stage.sh: the pycolmap fork's INVALID_POINT3D line is not the expected one" >&2; exit 1; }
cat >"$STAGE/st-shim/zstandard/__init__.py" <<'EOF'
"""Stand-in for zstandard on the path of gsplat's simple_trainer runs only (written by
experiments/gpu/stage.sh). viser imports zstandard at module level but uses it only to compress
messages for a connected browser; the runs pass --disable_viewer, so nothing here is called."""


class ZstdCompressor:
    def __init__(self, *args, **kwargs):
        raise RuntimeError("zstandard is a stand-in on this path (simple_trainer runs with --disable_viewer)")


ZstdDecompressor = ZstdCompressor
EOF

echo "== beer"
cp -r "$BEER" "$STAGE/beer"
chmod -R u+w "$STAGE/beer"

mib() { awk -v b="$1" 'BEGIN {printf "%.1f MiB", b / 1048576}'; }
# what a device call carries: tracked files, untracked files git does not ignore, the checkout's
# shared/ (ignored, but it travels) and the carried stage
tree_b=$( (git ls-files -z; git ls-files -z --others --exclude-standard) | xargs -0 du -cb 2>/dev/null \
    | awk '$2 == "total" {s += $1} END {print s + 0}')
shared_b=0
[[ -d shared ]] && shared_b=$(du -sb shared | cut -f1)
total() { echo $(($(du -sb "$STAGE" | cut -f1) + tree_b + shared_b)); }
if (($(total) > LIMIT_MIB * 1048576)); then
    echo "== pycolmap ${PYCOLMAP[0]} does not fit: ${PYCOLMAP[1]} instead"
    rm "$STAGE"/wheels/pycolmap-*.whl
    download_wheels "$STAGE/wheels" "pycolmap==${PYCOLMAP[1]}"
fi

(cd "$STAGE" && find . -type f ! -name MANIFEST.txt -print0 | sort -z | xargs -0 sha256sum) >"$STAGE/MANIFEST.txt"
stage_b=$(du -sb "$STAGE" | cut -f1)
total_b=$(total)
echo "== size: $STAGE $(mib "$stage_b") + working tree $(mib "$tree_b") + shared/ $(mib "$shared_b") = $(mib "$total_b") (limit $LIMIT_MIB MiB)"
for f in "$STAGE"/wheels/*.whl "$STAGE"/gsplat-1.5.3.tar.gz; do printf '   %8s  %s\n' "$(mib "$(stat -c %s "$f")")" "${f#"$STAGE"/}"; done
printf '   %8s  %s\n' "$(mib "$(du -sb "$STAGE/beer" | cut -f1)")" beer/
if ((total_b > LIMIT_MIB * 1048576)); then
    echo "stage.sh: $(mib "$total_b") is over the $LIMIT_MIB MiB limit" >&2
    exit 1
fi
