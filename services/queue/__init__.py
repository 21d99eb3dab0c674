"""The job queue and the per-job event streams.

``base``         the interfaces (``JobQueue``, ``Lease``, ``EventBus``)
``redis_queue``  Redis Streams with a consumer group: at-least-once delivery, leases renewed by
                 the worker, a reaper (XAUTOCLAIM) that hands a dead worker's job to another
``local``        the embedded default: an in-process queue and event bus, no Redis
"""
