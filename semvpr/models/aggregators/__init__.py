"""Aggregators: local features and a per-location mask → one global descriptor (``base.Aggregator``)."""
