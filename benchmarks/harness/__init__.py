"""The benchmark harness: datasets, methods and pipelines, perturbations, runner, renderer."""
