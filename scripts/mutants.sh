#!/usr/bin/env bash
# Mutation testing of the error-propagation and p-value code with cargo-mutants (not run in
# CI: hours on 2 cores). Each mutant (an operator flipped, a constant or a return value
# replaced, ...) is built and a test subset is run; a mutant whose tests still pass
# "survives" and needs a test or an explanation (docs/testing.md).
#
#   scripts/mutants.sh                     # every group below, each with its own tests
#   scripts/mutants.sh stats photometry    # some groups
#   scripts/mutants.sh pipeline/src/stats/ks.rs ...   # these files, tests from MUTANTS_TESTS
#   scripts/mutants.sh --summary [DIR]     # kill rate per file of the results under DIR
#
# Settings (environment):
#   MUTANTS_TESTS="--lib -- stats::"   cargo test arguments for files given by path
#                                      (default: the pipeline crate's unit tests)
#   MUTANTS_OUT=target/mutants-out     results: MUTANTS_OUT/<group>/mutants.out/
#   MUTANTS_SLOT=2                     a second source clone and build directory, so two
#                                      runs can go side by side (one core each)
#   MUTANTS_SHARD=0/4                  a quarter of the mutants (cargo-mutants --shard)
#   MUTANTS_ITERATE=1                  resume: skip the mutants an earlier run in the same
#                                      output directory caught (cargo-mutants --iterate)
#   MUTANTS_TIMEOUT=300                seconds a mutant's tests may take
#
# The mutants are applied in a clone of HEAD (target/mutants-tree[-SLOT], brought to HEAD
# at every run), never in the working tree; its build directory
# (target/mutants-target[-SLOT], profile `mutants`: release code, incremental) is kept
# between runs, so after the first build a mutant costs an incremental rebuild (~6 s on a
# quiet 2-core machine) plus its tests. Needs `cargo install cargo-mutants` (version 27).
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
out_root="$(cd "$root" && realpath -m "${MUTANTS_OUT:-target/mutants-out}")"

# The groups: the files whose mutants are counted, and the tests that judge them. The two
# Monte Carlo covariance tests of the joint calibration (~40 s together) are left out of
# the first pass; `--iterate` with MUTANTS_TESTS="--lib" re-judges the survivors with them.
slow="--skip the_covariance_with_the_telescope_matches --skip joint_covariance_matches_the_scatter"
group_files() {
    case "$1" in
        stats) echo "pipeline/src/stats/ks.rs pipeline/src/stats/kuiper.rs pipeline/src/stats/binomial.rs" ;;
        photometry) echo "pipeline/src/photometry/measure.rs pipeline/src/photometry/aperture.rs" ;;
        inversion) echo "pipeline/src/stokes/inversion.rs" ;;
        calibration) echo "pipeline/src/stokes/calibration.rs pipeline/src/calibration.rs" ;;
        reduce) echo "pipeline/src/reduce/beams.rs pipeline/src/reduce/entry.rs" ;;
        *) return 1 ;;
    esac
}
# The tests of a group: the test targets (`--lib`, `--test NAME`), given to every cargo
# invocation so that a mutant's build compiles only them (building every test target of the
# crate made a mutant cost 30-170 s instead of seconds), then `--` and the test filters.
# The reduce group's filters: the lib's reduce:: tests and every test of its three
# integration targets (a filter is a substring of a test's path; these name them all).
reduce_tests="reduce:: brightest median_offset eo_offset combine_geometry primary_of noiseless lone_star unpolarized_faint saturated one_dither near_equal_faint"
group_tests() {
    case "$1" in
        stats) echo "--lib -- stats::tests_pvalues stats::tests::k stats::tests::binomial stats::tests_errors::ks_" ;;
        photometry) echo "--lib -- photometry:: --skip photometry::psf_fit::joint" ;;
        inversion) echo "--lib -- stokes:: $slow" ;;
        calibration) echo "--lib -- stokes:: calibration:: $slow" ;;
        reduce) echo "--lib --test reduce_locate --test reduce_noiseless --test reduce_hard_cases -- $reduce_tests" ;;
    esac
}
all_groups=(stats photometry inversion calibration reduce)

# Kill rate per file over every outcome under a directory: (caught + timeout) / (caught +
# missed + timeout). A timeout is a mutant whose tests did not finish within
# MUTANTS_TIMEOUT (for these files an endless loop: the tests did not let it pass; each is
# read, docs/testing.md); unviable mutants (that do not build) are counted apart. A group's history.txt
# (the outcomes of its earlier runs, kept by `run` below because `--iterate` moves them
# away) is read first, then its latest run; a mutant's latest outcome counts.
outcomes() {
    local out="$1/mutants.out"
    for kind in caught missed timeout unviable; do
        [[ -f "$out/$kind.txt" ]] && sed "s/^/$kind /" "$out/$kind.txt"
    done
    return 0
}
summary() {
    local dir="$1" current args=()
    for g in "${all_groups[@]}"; do
        for f in $(group_files "$g"); do
            args+=(--file "$f")
        done
    done
    # The mutants of the code as it is now (the working tree; listing builds nothing): an
    # outcome recorded under a name the code no longer has (its line moved) is not counted,
    # and a mutant never judged on the present code is counted as untested.
    current="$(cd "$root" && cargo mutants --list --package sofipol-pipeline "${args[@]}")"
    printf '%-40s %7s %7s %7s %7s %8s %9s\n' file caught missed timeout unviable untested "kill rate"
    {
        sed 's/^/current /' <<<"$current"
        for group in "$dir"/*/; do
            [[ -f "$group/history.txt" ]] && cat "$group/history.txt"
            outcomes "$group"
        done
    } | awk '{kind = $1; $1 = ""; name = substr($0, 2)}
        kind == "current" {now[name] = 1; next}
        {last[name] = kind}
        END {
            for (name in now) {
                split(name, a, ":"); f = a[1]; files[f] = 1
                n[f SUBSEP ((name in last) ? last[name] : "untested")]++
            }
            for (f in files) {
                c = n[f SUBSEP "caught"] + 0; m = n[f SUBSEP "missed"] + 0
                t = n[f SUBSEP "timeout"] + 0; u = n[f SUBSEP "unviable"] + 0
                x = n[f SUBSEP "untested"] + 0; tested = c + m + t
                printf "%-40s %7d %7d %7d %7d %8d %8.1f%%\n", f, c, m, t, u, x, tested ? 100 * (c + t) / tested : 0
            }
        }' | sort
}

if [[ "${1:-}" == "--summary" ]]; then
    summary "${2:-$out_root}"
    exit 0
fi

cargo mutants --version >/dev/null 2>&1 || {
    echo "mutants.sh: cargo-mutants is not installed (cargo install cargo-mutants)" >&2
    exit 1
}
suffix="${MUTANTS_SLOT:+-$MUTANTS_SLOT}"
tree="$root/target/mutants-tree$suffix"
export CARGO_TARGET_DIR="$root/target/mutants-target$suffix"
# Bring the clone to HEAD; files that did not change keep their times, so the kept build
# directory stays incremental.
if [[ -d "$tree/.git" ]]; then
    git -C "$tree" fetch --quiet "$root" HEAD
    git -C "$tree" reset --quiet --hard FETCH_HEAD
    git -C "$tree" clean --quiet -fdx
else
    rm -rf "$tree"
    git clone --quiet --local --no-hardlinks "$root" "$tree"
    git -C "$tree" checkout --quiet "$(git -C "$root" rev-parse HEAD)"
fi
if [[ -n "$(git -C "$root" status --porcelain --untracked-files=no)" ]]; then
    echo "mutants.sh: testing HEAD ($(git -C "$root" rev-parse --short HEAD)); uncommitted changes are left out" >&2
fi

# The dependencies built first, one slot at a time: fitsio-sys configures and builds its
# bundled cfitsio inside cargo's registry sources, so two first builds at once (two slots
# started together on a fresh machine) break each other's baseline.
mkdir -p "$root/target"
(
    cd "$tree"
    flock "$root/target/mutants-deps.lock" \
        cargo build --quiet --profile mutants --package sofipol-pipeline --lib
)

# run NAME "FILES" "TESTS": TESTS is "TARGETS -- FILTERS" (cargo test's own syntax)
run() {
    local name="$1" files="$2" tests="$3" args=()
    for f in $files; do
        args+=(--file "$f")
    done
    [[ -n "${MUTANTS_ITERATE:-}" ]] && args+=(--iterate)
    [[ -n "${MUTANTS_SHARD:-}" ]] && args+=(--shard "$MUTANTS_SHARD")
    local -a words filters=()
    read -r -a words <<<"$tests"
    local seen_dashes=""
    for w in "${words[@]}"; do
        if [[ -n "$seen_dashes" ]]; then
            filters+=("$w")
        elif [[ "$w" == "--" ]]; then
            seen_dashes=1
        else
            args+=("--cargo-arg=$w")
        fi
    done
    mkdir -p "$out_root/$name"
    outcomes "$out_root/$name" >>"$out_root/$name/history.txt"
    echo "mutants.sh: $name: $files; tests: cargo test $tests" >&2
    (
        cd "$tree"
        time cargo mutants \
            --package sofipol-pipeline \
            --in-place \
            --profile mutants \
            --timeout "${MUTANTS_TIMEOUT:-300}" \
            --build-timeout "${MUTANTS_BUILD_TIMEOUT:-1200}" \
            --output "$out_root/$name" \
            "${args[@]}" \
            -- -- "${filters[@]}"
    ) || true # survivors make cargo-mutants exit non-zero; the summary says what happened
}

if [[ $# -eq 0 ]]; then
    set -- "${all_groups[@]}"
fi
if [[ "$1" == *.rs ]]; then
    run files "$*" "${MUTANTS_TESTS:---lib}"
else
    for g in "$@"; do
        files="$(group_files "$g")" || {
            echo "mutants.sh: no group '$g' (groups: ${all_groups[*]}; or give files)" >&2
            exit 2
        }
        run "$g" "$files" "${MUTANTS_TESTS:-$(group_tests "$g")}"
    done
fi
summary "$out_root"
