"""What every layer stands on: user errors, file output and containment, stage lines, compute
precision, the artifact cache, checkpoint files read as data, typed settings. Imports nothing else of semvpr."""
