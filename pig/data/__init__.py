"""Capture formats (THuman4, DNA-Rendering), the synthetic capture and the preprocessed capture."""
