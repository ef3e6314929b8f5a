"""The project's benchmarks and measurement scripts (repository only: not part of the wheel).

Each script is a module run from the repository root:

    python -m benchmarks.bench_metrics --json

Shared pieces live in named modules: `benchmarks.provenance` (the machine / provenance record every
JSON result carries), `benchmarks.common` (shared data paths, small helpers) and `benchmarks.curves`
(validation curves of a training run's checkpoints). Scoring a checkpoint is the product's own
`fastocc.infer.score`.
"""
