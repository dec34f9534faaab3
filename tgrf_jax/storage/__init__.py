"""Files the tools write and read back: checksummed checkpoints, run-directory locks and atomic writes. Nothing
here knows about the simulator or the trainer."""
