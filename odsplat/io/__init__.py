"""Importers: video and signal files from other equipment, read into odsplat's in-memory types."""
