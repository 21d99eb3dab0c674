"""Training of the fields ``L_phi`` and ``dL_theta`` by their residuals (paper Sec. 4, 6.1):
the residual estimators (:mod:`.residuals`), the pool of residual batches (:mod:`.pool`), the
step schedule (:mod:`.schedule`) and the trainer that owns the fields (:mod:`.trainer`)."""

from services.solver.training.steps import StepStats
from services.solver.training.trainer import FieldTrainer, fields_of, trainer_for

__all__ = ["FieldTrainer", "StepStats", "fields_of", "trainer_for"]
