"""The runtime every command shares: machine settings, model loading, scene preparation, source choice,
evaluation protocols, training, fine-tuning's tuner, checkpoints and reports."""
