#!/usr/bin/env bash
# Fetch the wheels the GPU machine's image lacks (benchmarks/gpu_wheels.txt) for its Python 3.12 on
# manylinux x86_64 into a git-ignored folder, build the fit rows' dataset into another (rendering works here,
# the GPU machine may have no OpenGL), and print the one command to run there.
#
#   benchmarks/gpu_prepare.sh [DIR [DATASET]]   # defaults: .gpu_wheels and .gpu_dataset at the repository root
#
# DIR ends up holding exactly the listed wheels (older ones and an installed DIR/site are removed); DATASET is
# rebuilt from scratch (benchmarks/gpu_check.py --build-dataset: 3 procedural categories x 6 objects, 64 px,
# 3 views per set, R = 32, about 1 MB). The printed command runs from the repository root on the GPU machine,
# with DIR and DATASET travelling beside the working tree; $OUT there is the folder whose files come back.
set -euo pipefail

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
dir="${1:-$root/.gpu_wheels}"
dataset="${2:-$root/.gpu_dataset}"
list="$root/benchmarks/gpu_wheels.txt"
python="${PYTHON:-python3}"

mkdir -p "$dir"
dir="$(cd "$dir" && pwd)"
new="$(mktemp -d "$dir/.download.XXXXXX")"
trap 'rm -rf "$new"' EXIT

count=0
while IFS= read -r line || [[ -n "$line" ]]; do
    requirement="${line%%#*}"
    requirement="${requirement//[[:space:]]/}"
    [[ -z "$requirement" ]] && continue
    if [[ "$line" == *"# build"* ]]; then
        # a pure-Python project without a wheel on PyPI: build its (py3-none-any) wheel from the source
        "$python" -m pip wheel --quiet --disable-pip-version-check --no-deps --no-binary=:all: \
            --wheel-dir "$new" "$requirement"
    else
        # one requirement per call: the list pins two versions of diffusers, which one pip call refuses
        "$python" -m pip download --quiet --disable-pip-version-check --no-deps --only-binary=:all: \
            --python-version 3.12 --implementation cp \
            --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
            --dest "$new" "$requirement"
    fi
    count=$((count + 1))
done < "$list"

found=$(find "$new" -maxdepth 1 -name '*.whl' | wc -l)
if [[ "$found" -ne "$count" ]]; then
    echo "gpu_prepare.sh: $list names $count wheels, $found were downloaded into $new" >&2
    exit 1
fi
rm -f "$dir"/*.whl
rm -rf "$dir/site"
mv "$new"/*.whl "$dir"/

rm -rf "$dataset"
"$python" "$root/benchmarks/gpu_check.py" --build-dataset "$dataset"

rel="${dir#"$root"/}"
data_rel="${dataset#"$root"/}"
echo "$found wheels in $dir ($(du -sh "$dir" | cut -f1)):"
(cd "$dir" && ls -1 ./*.whl | sed 's|^\./|  |')
echo "the fit rows' dataset in $dataset ($(du -sh "$dataset" | cut -f1))"
echo
echo "Carry $rel and $data_rel with the working tree, then run from the repository root on the GPU machine"
echo "(only the fit rows, without the renderer probe: add --no-render --rows 'fit: Pix2Vox++ tiny + callback,fit: LRGT tiny + callback'):"
echo
echo "python3 benchmarks/gpu_check.py --wheels $rel --dataset $data_rel --out \"\$OUT\" --budget-s 420"
