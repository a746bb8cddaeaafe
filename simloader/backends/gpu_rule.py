"""The rule `auto` estimates a GPU engine's steps/s by: a fixed latency per step of the batch
(its kernel launches, a CUDA graph's replay, XLA's loop) plus a cost per trajectory once the
GPU is busy, both scaled by the model's own step time on one CPU core. Each GPU engine's entry
holds its fitted constants."""

from __future__ import annotations

from simloader.backends.contract import Job

Constants = tuple[tuple[float, float], tuple[float, float]]


def steps_per_second(job: Job, constants: dict[bool, Constants]) -> float:
    """`nbatch / (floor + nbatch * cost)` for `job`; `constants[contacts]` is
    ((floor seconds, floor in step times), (cost seconds, cost in step times))."""
    (floor_s, floor_k), (cost_s, cost_k) = constants[job.contacts]
    per_step = floor_s + floor_k * job.step_s + job.nbatch * (cost_s + cost_k * job.step_s)
    return job.nbatch / per_step
