"""The job queue, the per-job event streams and the stream slots.

``base``         the interfaces and the queue's contract (one marker per job, owned deliveries,
                 attempt heartbeats, adoption after Redis lost its data)
``redis_queue``  Redis Streams with a consumer group and a few Lua scripts: at-least-once delivery,
                 leases renewed by the worker, takeover (XAUTOCLAIM) of a silent worker's job
``local``        the embedded default: the same contract in-process, no Redis
"""
