"""Anchors, levels of detail, decoders and the avatar model."""
