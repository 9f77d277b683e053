#!/usr/bin/env bash
# Fetch the wheels the GPU machine's image lacks (benchmarks/gpu_wheels.txt) for its Python 3.12 on
# manylinux x86_64, into a git-ignored folder, and print the one command to run there.
#
#   benchmarks/gpu_prepare.sh [DIR]     # DIR: default .gpu_wheels at the repository root
#
# DIR ends up holding exactly the listed wheels (older ones and an installed DIR/site are removed).
# The printed command runs from the repository root on the GPU machine, with DIR travelling beside the
# working tree; $OUT there is the folder whose files come back.
set -euo pipefail

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
dir="${1:-$root/.gpu_wheels}"
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

rel="${dir#"$root"/}"
echo "$found wheels in $dir ($(du -sh "$dir" | cut -f1)):"
(cd "$dir" && ls -1 ./*.whl | sed 's|^\./|  |')
echo
echo "Carry $rel with the working tree, then run from the repository root on the GPU machine:"
echo
echo "python3 benchmarks/gpu_check.py --wheels $rel --out \"\$OUT\" --budget-s 420"
