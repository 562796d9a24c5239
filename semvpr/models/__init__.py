"""Models: backbones, aggregators (NetVLAD, SRAL), mask sources, retriever, teacher, student."""
