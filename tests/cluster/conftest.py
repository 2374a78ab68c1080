"""tests/cluster holds opt-in checks on a real cluster (bash tests/cluster/slurm.sh), not pytest tests."""

collect_ignore_glob = ["*"]
