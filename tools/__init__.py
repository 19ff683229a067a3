"""Command line and offline jobs: dataset, train, evaluate, bench, replay, inspect."""
