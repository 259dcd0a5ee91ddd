"""Config groups of indreg-train-momentum (``model=oneshot`` | ``model=unrolled``), on its Hydra search path."""
