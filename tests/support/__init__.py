"""What the tests share, and the only part of ``tests`` the bench may import (an import-linter
contract): processes of the service and a throw-away Redis (:mod:`~tests.support.cluster`,
:mod:`~tests.support.service`), moto's S3 server (:mod:`~tests.support.s3server`), the chaos
harness (:mod:`~tests.support.chaos`), Chromium for the dashboard (:mod:`~tests.support.browser`),
and the scenes and files the tests build (:mod:`~tests.support.scenes`,
:mod:`~tests.support.hard_scenes`, :mod:`~tests.support.payloads`). Test modules import helpers
from here, never from each other, so that moving a test file between tier folders changes no
import."""
