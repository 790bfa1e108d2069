"""What a run keeps on disk: learner checkpoints, the replay's log and snapshots, metrics and
TensorBoard events."""
