"""The queue consumer: ``ndrf worker`` (Redis) or threads inside ``ndrf serve`` (embedded)."""
