"""Networks only: backbones, aggregators, mask sources, the teacher and the student."""
