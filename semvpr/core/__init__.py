"""What every layer stands on: user errors, file output and containment, stage lines, compute
precision, the artifact cache, checkpoint records and resuming. Imports nothing else of semvpr."""
