"""omnirecon's benchmarks: every number in BENCHMARKS.md comes from here.

    python -m bench --help            # the benchmarks, one line each
    python -m bench <name> [args]     # run one (``python -m bench <name> --help`` for its options)
    python -m bench page [--reuse]    # run them all (or reuse bench/results/*.json) and write BENCHMARKS.md

Each measuring module ``bench/<name>.py`` has ``main(argv)`` and writes results JSON with a provenance
header into ``bench/results/``; ``bench/report/`` turns that JSON into the Markdown of each section.
"""
