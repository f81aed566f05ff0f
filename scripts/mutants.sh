#!/usr/bin/env bash
# Mutation testing of the error-propagation and p-value code with cargo-mutants (not run in
# CI: hours on 2 cores). Each mutant (an operator flipped, a constant or a return value
# replaced, ...) is built and the test subset below is run; a mutant whose tests still pass
# "survives" and needs a test or an explanation (docs/testing.md).
#
#   scripts/mutants.sh                        # all the files below
#   scripts/mutants.sh pipeline/src/stats/ks.rs ...   # only these files
#   MUTANTS_SHARD=0/4 scripts/mutants.sh       # a quarter of the mutants (cargo-mutants --shard)
#   MUTANTS_TESTS="--lib --test reduce_locate" scripts/mutants.sh   # another test subset
#   MUTANTS_TESTS="--lib -- stats::" scripts/mutants.sh pipeline/src/stats/ks.rs   # unit tests of a module
#   MUTANTS_OUT=target/mutants-stats scripts/mutants.sh ...   # results elsewhere (default target/mutants-out)
#   MUTANTS_ITERATE=1 scripts/mutants.sh ...  # resume: skip the mutants already caught there (--iterate)
#
# The mutants are applied in a clone of HEAD (target/mutants-tree, refreshed every run), so
# the working tree is never touched; its build directory (target/mutants-target, profile
# `mutants`: release code, incremental) is kept between runs. Results: target/mutants-out/
# mutants.out/{caught,missed,timeout,unviable}.txt and outcomes.json. Needs
# `cargo install cargo-mutants` (version 27 used).
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
files=("$@")
if [[ ${#files[@]} -eq 0 ]]; then
    files=(
        pipeline/src/stokes/inversion.rs
        pipeline/src/stokes/calibration.rs
        pipeline/src/calibration.rs
        pipeline/src/photometry/measure.rs
        pipeline/src/photometry/aperture.rs
        pipeline/src/reduce/beams.rs
        pipeline/src/reduce/entry.rs
        pipeline/src/stats/ks.rs
        pipeline/src/stats/kuiper.rs
        pipeline/src/stats/binomial.rs
    )
fi
cargo mutants --version >/dev/null 2>&1 || {
    echo "mutants.sh: cargo-mutants is not installed (cargo install cargo-mutants)" >&2
    exit 1
}
tree="$root/target/mutants-tree"
rm -rf "$tree"
git clone --quiet --local --no-hardlinks "$root" "$tree"
# Uncommitted changes are not tested: say so.
if [[ -n "$(git -C "$root" status --porcelain --untracked-files=no)" ]]; then
    echo "mutants.sh: testing HEAD ($(git -C "$root" rev-parse --short HEAD)); uncommitted changes are left out" >&2
fi
args=()
for f in "${files[@]}"; do
    args+=(--file "$f")
done
if [[ -n "${MUTANTS_ITERATE:-}" ]]; then
    args+=(--iterate)
fi
if [[ -n "${MUTANTS_SHARD:-}" ]]; then
    args+=(--shard "$MUTANTS_SHARD")
fi
# The test subset: the pipeline crate's unit tests (the numerical references of photometry,
# Stokes inversion, calibration, statistics and the e-o offset) plus, by default, the
# integration tests of the reduction's locating stages and of noiseless inversions.
read -r -a tests <<<"${MUTANTS_TESTS:---lib --test reduce_locate --test reduce_noiseless}"
cd "$tree"
export CARGO_TARGET_DIR="$root/target/mutants-target"
time cargo mutants \
    --package sofipol-pipeline \
    --in-place \
    --profile mutants \
    --timeout "${MUTANTS_TIMEOUT:-300}" \
    --build-timeout "${MUTANTS_BUILD_TIMEOUT:-1200}" \
    --output "$(cd "$root" && realpath -m "${MUTANTS_OUT:-target/mutants-out}")" \
    "${args[@]}" \
    -- "${tests[@]}"
