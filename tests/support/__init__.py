"""What only the tests share: the store a service process uses and its SSE events
(:mod:`~tests.support.service`), Chromium for the dashboard (:mod:`~tests.support.browser`), the
scenes and files the tests build (:mod:`~tests.support.scenes`, :mod:`~tests.support.hard_scenes`,
:mod:`~tests.support.payloads`), in-process jobs (:mod:`~tests.support.jobs`), the attack helpers
(:mod:`~tests.support.attack`) and the linear models of the optimizer tests
(:mod:`~tests.support.linear`). What the bench uses too (processes of the service, Redis, moto's S3
server, the chaos harness) is the top-level :mod:`harness` package: the bench may not import the
tests (an import-linter contract). Test modules import helpers from here or from ``harness``, never
from each other, so that moving a test file between tier folders changes no import."""
