"""The artifact store: job folders, atomic writes, images."""
