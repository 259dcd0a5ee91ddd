"""Train a learned initial momentum: ``python scripts/train_momentum.py [key=value ...]`` (Hydra config
``indreg/learn/conf/train_momentum.yaml``); data parallel: ``torchrun --standalone --nproc_per_node=2 scripts/train_momentum.py``."""
from indreg.learn.train import main

if __name__ == "__main__":
    main()
