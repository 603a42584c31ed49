"""The task protocol: the one TensorDict key under which task identifiers travel.

Every task distribution (p0, the flow adversary p_φ) returns its samples under :data:`TASK_KEY`,
every collector reads the identifiers of its tasks there, and every env takes them under the same
key in its reset TensorDict (declared in its specs, so TorchRL transforms, batched envs and
collectors forward it) and reports them there with every step.
"""

from __future__ import annotations

TASK_KEY = "params"
"""TensorDict key of the task identifiers, a float tensor ``[..., task_dim]``."""
