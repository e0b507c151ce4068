"""Ingest: the aggregator (the one writer of held segments), the segment store and its spill."""
