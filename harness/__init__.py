"""What the tests and the bench both use to run the service on this machine: ``ndrf serve`` and
``ndrf worker`` processes, a throw-away Redis, a JSON client of the API and a small job
(:mod:`~harness.cluster`), moto's S3 server on loopback (:mod:`~harness.s3server`) and the chaos
harness (:mod:`~harness.chaos`). It imports neither ``tests`` nor ``bench`` (import-linter
contracts), so both may import it; what only the tests need stays in ``tests/support``."""
