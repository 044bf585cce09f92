"""Preprocessing of one or many scenes on Ray (``langfield preprocess SCENE... --address ...``).

The driver plans every scene as :func:`~langfield.io.preprocess.preprocess_scene` does (checks the
scene, records ``depth_kind``, skips the views whose files are already valid), then hands the views left
to a pool of Ray actors, one CPU each and no more actors than views. Each actor builds the models once,
with the picklable ``make_models`` (``functools.partial(load_models, ...)``), keeps each scene it has
met, and writes the same files as a local run, atomically: an interrupted run resumes where it stopped.

On a cluster the scenes and the model folders must be at the same paths on every node (a shared file
system); docs/cluster.md.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path

from tqdm.auto import tqdm

from langfield.cluster import ray_session
from langfield.io.preprocess import (
    Models,
    PreprocessReport,
    ViewDone,
    add_view,
    finish_report,
    plan_scene,
    preprocess_view,
)
from langfield.io.scene import load_scene


class ViewWorker:
    """A Ray actor: the models, built once, and the scenes it has been given."""

    def __init__(self, make_models: Callable[[], Models]) -> None:
        self.models = make_models()
        self.scenes = {}

    def run(self, root: str, name: str, features: bool, depth: bool) -> tuple[str, str, ViewDone]:
        if root not in self.scenes:
            self.scenes[root] = load_scene(root, views=[0])
        m = self.models
        done = preprocess_view(self.scenes[root], name, m.segmenter, m.encoder, m.depth, features, depth)
        return root, name, done


def preprocess_on_ray(
    scene_dirs: Sequence[str | Path],
    models: Models,
    make_models: Callable[[], Models],
    *,
    address: str | None = None,
    overwrite: bool = False,
    progress: bool = True,
) -> list[PreprocessReport]:
    """Preprocesses the scenes' views on Ray; one report per scene, as the local run gives.

    Args:
        scene_dirs: scene folders.
        models: the models, built on the driver: every scene is planned and checked with them before a
            worker starts (their kinds and dimensions; they compute nothing here).
        make_models: builds the same models in each worker (picklable).
        address: a Ray cluster (``auto``, ``ray://host:10001``), or None for a local Ray in the process.
    """
    t_start = time.perf_counter()
    plans = [plan_scene(d, models.segmenter, models.encoder, models.depth, overwrite) for d in scene_dirs]
    jobs = [(str(scene.root), name, *need) for scene, _, todo in plans for name, need in todo.items()]
    reports = {str(scene.root): report for scene, report, _ in plans}
    seconds = {root: {"segmenter": 0.0, "encoder": 0.0, "depth": 0.0} for root in reports}
    with ray_session(address, needed=bool(jobs)) as ray:
        if jobs:
            from ray.util import ActorPool

            cpus = int(ray.available_resources().get("CPU", 1))
            actor = ray.remote(num_cpus=1)(ViewWorker)
            pool = ActorPool([actor.remote(make_models) for _ in range(max(1, min(cpus, len(jobs))))])
            results = pool.map_unordered(lambda a, job: a.run.remote(*job), jobs)
            with tqdm(total=len(jobs), desc="preprocess", unit="view", disable=not progress) as bar:
                for root, name, done in results:
                    add_view(reports[root], name, done, seconds[root])
                    bar.set_postfix_str(name)
                    bar.update()
    for root, report in reports.items():
        finish_report(report, seconds[root], t_start)
    return list(reports.values())
