"""Where the training loop runs: in this process (workers=0) or as a Ray Train worker.

Both sessions give the loop the same things (see loop.TrainSession): this worker's batches, the
run's newest checkpoint, a place to stage a checkpoint, a collective `report`, DDP wrapping and a
mean over workers.
"""

from __future__ import annotations

import contextlib
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from core.device import resolve_device
from services.training.checkpoints import LocalCheckpointStore, newest_complete_checkpoint
from services.training.config import TrainJobConfig
from services.training.seeding import shuffle_seed

# Records in the local shuffle buffer of each Ray worker (a few batches' worth mixes within shards).
SHUFFLE_BUFFER_RECORDS = 16
# A Ray worker may use CUDA only with a GPU share, whatever the machine has: the error says how to get one.
NO_GPU_SHARE = "to this worker (use --device cpu, or --gpus-per-worker 1 on a GPU machine)"


class LocalSession:
    """The in-process loop: one worker, records read straight from the shards, local checkpoints."""

    rank = 0
    world_size = 1
    skips_into_epochs = True   # its shuffled epochs are plain index lists (epoch_batches' skip)

    @property
    def progress_stream(self):
        return sys.stdout  # looked up on use: the caller (or pytest) may have replaced it

    def __init__(self, config: TrainJobConfig, *, dataset=None) -> None:
        """dataset: anything with len() and [i] → record; default: ShardDataset(config.data_dir)."""
        if dataset is None:
            from core.data.shards import ShardDataset

            dataset = ShardDataset(config.data_dir)
        self.dataset = dataset
        self.config = config
        self.device = resolve_device(config.device)
        self.store = LocalCheckpointStore(config.local_checkpoint_root, keep=config.keep_checkpoints)

    def epoch_batches(self, epoch: int, skip: int = 0):
        """skip: batches of this epoch already trained (a resume of a run stopped by a signal)."""
        order = np.random.default_rng([self.config.seed, epoch]).permutation(len(self.dataset))
        size = self.config.batch_size
        for start in range(skip * size, len(order) - size + 1, size):  # drop the last partial batch
            yield [self.dataset[int(i)] for i in order[start:start + size]]

    @contextlib.contextmanager
    def latest_checkpoint(self):
        # the newest complete one, as the driver picks (job.latest_checkpoint_dir): a dir left torn by an older
        # n3dmap's deletion is passed over rather than failed on
        yield newest_complete_checkpoint(self.store.root)

    def staging_dir(self, step: int) -> Path:
        self.store.root.mkdir(parents=True, exist_ok=True)
        return Path(tempfile.mkdtemp(prefix=f".staging_{step}_", dir=self.store.root))

    def report(self, metrics: dict, step: int, checkpoint_dir) -> None:
        if checkpoint_dir is not None:
            self.store.commit(Path(checkpoint_dir), step)

    def prepare_model(self, model: torch.nn.Module) -> torch.nn.Module:
        return model

    def all_reduce_mean(self, values: torch.Tensor) -> torch.Tensor:
        return values


class RaySession:
    """A Ray Train worker: dataset shard from `get_dataset_shard`, checkpoints through `report`."""

    skips_into_epochs = False   # a streamed shard with a local shuffle buffer has no index to start from

    def __init__(self, config: TrainJobConfig) -> None:
        import ray.train
        import ray.train.torch

        import ray.data

        ray.data.DataContext.get_current().enable_progress_bars = False
        context = ray.train.get_context()
        self.config = config
        self.rank = context.get_world_rank()
        self.world_size = context.get_world_size()
        self.device = resolve_device(config.device, where=NO_GPU_SHARE,
                                     cuda_available=config.gpus_per_worker > 0 and torch.cuda.is_available())
        if self.device.type == "cuda":
            self.device = ray.train.torch.get_device()
        self._shard = ray.train.get_dataset_shard("train")
        self.progress_stream = None  # the driver prints progress from metrics.jsonl

    def epoch_batches(self, epoch: int, skip: int = 0):
        from services.training.data import decode_rows

        if skip:  # only a signal-stopped in-process run saves a data position, and runs resume in their own mode
            raise ValueError(f"a Ray Train worker cannot skip into an epoch (skip={skip})")

        for batch in self._shard.iter_batches(
                batch_size=self.config.batch_size, batch_format="numpy", drop_last=True,
                local_shuffle_buffer_size=max(SHUFFLE_BUFFER_RECORDS, self.config.batch_size),
                local_shuffle_seed=shuffle_seed(self.config.seed, epoch, self.rank)):
            yield decode_rows(batch)

    @contextlib.contextmanager
    def latest_checkpoint(self):
        import ray.train

        checkpoint = ray.train.get_checkpoint()
        if checkpoint is None:
            # Ray Train registers a reported checkpoint asynchronously: a worker group that dies just
            # after `report` can be restarted without it although it is complete on storage. Resume
            # from the newest complete checkpoint there rather than from scratch.
            from services.training.checkpoints import newest_complete_checkpoint

            yield newest_complete_checkpoint(self.config.run_path / self.config.ray_storage_name)
        else:
            with checkpoint.as_directory() as directory:
                yield Path(directory)

    def staging_dir(self, step: int) -> Path:
        return Path(tempfile.mkdtemp(prefix=f"n3dmap_ckpt_{step}_"))

    def report(self, metrics: dict, step: int, checkpoint_dir) -> None:
        import ray.train
        from ray.train import Checkpoint

        from services.training.checkpoints import checkpoint_dir_name

        checkpoint = Checkpoint.from_directory(str(checkpoint_dir)) if checkpoint_dir else None
        ray.train.report(metrics, checkpoint=checkpoint, checkpoint_dir_name=checkpoint_dir_name(step))

    def prepare_model(self, model: torch.nn.Module) -> torch.nn.Module:
        import ray.train.torch

        # find_unused_parameters: a task's objective may leave some heads without a gradient.
        return ray.train.torch.prepare_model(
            model, move_to_device=True,
            parallel_strategy_kwargs={"find_unused_parameters": True})

    def all_reduce_mean(self, values: torch.Tensor) -> torch.Tensor:
        if self.world_size == 1 or not torch.distributed.is_initialized():
            return values
        values = values.clone()
        torch.distributed.all_reduce(values, op=torch.distributed.ReduceOp.SUM)
        return values / self.world_size
