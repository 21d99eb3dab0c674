"""Untrusted input: checks of uploaded scenes, meshes and images before anything parses them
for real, and the throw-away child processes in which scenes are loaded."""
