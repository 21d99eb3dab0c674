"""A short chaos run (:mod:`harness.chaos`): 3 jobs on 2 workers in Redis mode, one worker SIGKILLed
while it runs a job, then Redis killed and restarted empty while both workers are busy. Every job
must succeed, none be lost, and each job's event history (events name the attempt that wrote them)
must show one writer at a time: no attempt writes after its successor started."""

from __future__ import annotations

from harness.chaos import ChaosConfig, markdown, run


def test_kill_and_redis_restart_lose_nothing_and_fail_nothing(tmp_path):
    report = run(ChaosConfig(jobs=3, workers=2, iterations=8, kill_every=0.0, max_kills=1, redis_restart_after=0.0,
                             kills_before_redis=1, disk_full_after=None, lease_seconds=2.0, max_attempts=3,
                             timeout=240.0, folder=str(tmp_path)))
    print(markdown(report))
    assert [i["kind"] for i in report["incidents"]] == ["kill", "redis-restart"], report["incidents"]
    assert report["lost"] == [] and report["failed"] == 0, report["per_job"]
    assert report["succeeded"] == 3
    assert report["overlapping_writers"] == 0, report["per_job"]
    kill = report["kills"][0]
    assert kill["successor"] is not None and kill["successor"] != kill["attempt"]
    running_at_restart = report["incidents"][1]["detail"]["running"]
    assert len(running_at_restart) == 2          # both workers were busy when Redis lost its data
