"""Scenes: loading (built-in, XML with its files, dict), parameters, and what a scene contains."""
