"""The job-file reference page (docs/reference/job-file.md) is generated from the schemas: it must
be what ``python -m schemas.reference`` writes now, and list every field."""

from __future__ import annotations

from schemas.experiments import ExperimentSpec
from schemas.job import JobSpec, RenderSpec
from schemas.reference import PAGE, main, reference
from schemas.solver import TrainingConfig


def test_the_committed_reference_page_is_not_stale():
    assert PAGE.read_text() == reference(), "docs/reference/job-file.md is stale: run python -m schemas.reference"


def test_every_field_of_every_document_is_listed_with_its_description():
    page = reference()
    for model in (JobSpec, RenderSpec, TrainingConfig, ExperimentSpec):
        assert f"### {model.__name__}\n" in page
        for name, info in model.model_fields.items():
            assert f"| `{info.alias or name}` |" in page, name
            assert " ".join((info.description or "").split()).replace("|", "\\|")[:40] in page, name


def test_check_mode_fails_on_a_stale_page(tmp_path):
    stale = tmp_path / "job-file.md"
    stale.write_text(reference().replace("| `iterations` |", "| `iters` |"))
    assert main(["--out", str(stale), "--check"]) == 1
    assert main(["--out", str(stale)]) == 0 and main(["--out", str(stale), "--check"]) == 0
