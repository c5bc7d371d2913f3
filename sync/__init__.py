"""Sync: puts the sequential takes of a capture on one impact-locked timeline."""
