"""Constraint hooks that act on the sample after every denoising update.

The first two are the paper's (Dynamically Constraining Diffusion Policies During Inference);
the rest go further: a final projection (a hard guarantee for every waypoint), a repair of the
straight path between consecutive executed setpoints, and the committed prefix that lets a
chunk denoised in the background take over from the one executing without a jump. All work in
workspace pixels, batched over episodes and waypoints; the constraint hooks consult only the
`RestrictedArea` they are given.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from constrained_diffusion_ros.sampling.sampler import DenoisingStep, SampleHook
from constrained_diffusion_ros.zones.geometry import RestrictedArea


@dataclass
class Resampling:
    """Waypoints inside the area become `w z + (1 - w) x`, w falling linearly from 1 to 0.

    z is drawn around the centre of the action space: standard normal in the normalised
    space, mapped to pixels. Blending commutes with the affine map, so doing it in pixels is the
    same as doing it in the normalised space.
    """

    area: RestrictedArea

    def __call__(self, sample: Tensor, step: DenoisingStep) -> Tensor:
        inside = self.area.contains(sample)
        return self.blend(sample, inside, step) if inside.any() else sample

    @staticmethod
    def blend(sample: Tensor, inside: Tensor, step: DenoisingStep) -> Tensor:
        """The waypoints `inside` blended with fresh draws."""
        weight = 1.0 - step.progress
        fresh = step.normalizer.unnormalize(torch.randn(sample.shape, generator=step.generator))
        blended = weight * fresh + (1.0 - weight) * sample
        return torch.where(inside[..., None], blended, sample)


@dataclass
class GradientPush:
    """Waypoints inside the area move `step_size` pixels along the way out (nearest boundary)."""

    area: RestrictedArea
    step_size: float

    def __call__(self, sample: Tensor, step: DenoisingStep) -> Tensor:
        inside, outward = self.area.inside_and_outward(sample)
        if outward is None:
            return sample
        return torch.where(inside[..., None], sample + self.step_size * outward, sample)


@dataclass
class ResamplingThenPush:
    """`Resampling` and then `GradientPush` on one area, as the two hooks in turn would act,
    with one zone query fewer where no waypoint is inside: resampling leaves the sample as it
    was, so the push would find none inside either."""

    area: RestrictedArea
    step_size: float

    def __post_init__(self) -> None:
        self._push = GradientPush(self.area, self.step_size)

    def __call__(self, sample: Tensor, step: DenoisingStep) -> Tensor:
        inside = self.area.contains(sample)
        if not inside.any():
            return sample
        return self._push(Resampling.blend(sample, inside, step), step)


@dataclass
class FinalProjection:
    """After the last update, every waypoint inside (or within `margin`) moves to the nearest
    point `margin` outside: no commanded setpoint can lie in the area."""

    area: RestrictedArea
    margin: float = 1.0

    def __call__(self, sample: Tensor, step: DenoisingStep) -> Tensor:
        if step.index != step.total - 1:
            return sample
        return self.area.project_out(sample, self.margin)


@dataclass
class PathRepair:
    """After the last update, the straight path pusher -> first executed waypoint -> ... must
    not enter the area: a waypoint whose incoming segment enters has its step turned as little
    as it must be (`slide`, the default; up to 150 degrees either way, its length kept where it
    can be) for the segment to be free and its end `margin` px outside, so the path goes along
    the zone's side and on. Where no turn is free, or with `slide=False`, it is pulled back
    along the segment to just before the entry, which stops the path in front of the zone. The
    check runs again from there.

    Segments that start inside (the pusher already in a zone) cannot be repaired this way and
    are left to the projection and the next replanning.
    """

    area: RestrictedArea
    start: Tensor  # (B, 2) pusher positions when the chunk is planned
    first_index: int = 1
    margin: float = 1.0
    from_progress: float = 1.0  # < 1: also after the updates from this progress on, so the
    # updates after a repair can adapt the rest of the chunk to it
    slide: bool = True

    def __call__(self, sample: Tensor, step: DenoisingStep) -> Tensor:
        if step.index != step.total - 1 and step.progress < self.from_progress:
            return sample
        head, path = sample[:, : self.first_index], sample[:, self.first_index:]
        # Zones that move are forecast per waypoint (`zones.motion.Forecast`): segment k is
        # checked against them as they will be when waypoint k runs.
        columns = getattr(self.area, "columns", None)
        area = columns(self.first_index) if columns is not None else self.area
        for _ in range(path.shape[1]):
            starts = torch.cat([self.start[:, None].to(path), path[:, :-1]], dim=1)
            clear = area.segment_clear_fraction(starts, path)
            # A segment that ends on the boundary is clear all the way, yet its end may test
            # inside (points on the boundary test either way): that counts as entering too.
            entering = ((clear < 1.0) | area.contains(path)) & ~area.contains(starts)
            if not entering.any():
                break
            first = entering.float().argmax(dim=1)  # first entering segment per episode
            rows = torch.nonzero(entering.any(dim=1)).flatten()
            cols = first[rows]
            seg_start, seg_end = starts[rows, cols], path[rows, cols]
            length = (seg_end - seg_start).norm(dim=-1).clamp_min(1e-9)
            keep = (clear[rows, cols] - self.margin / length).clamp_min(0.0)
            repaired = seg_start + keep[:, None] * (seg_end - seg_start)
            if self.slide:
                repaired = self._around(area, rows, cols, seg_start, seg_end, repaired)
            path = path.clone()
            path[rows, cols] = repaired.to(path)
        return torch.cat([head, path], dim=1)

    def _around(self, area: RestrictedArea, rows: Tensor, cols: Tensor, seg_start: Tensor,
                seg_end: Tensor, pulled_back: Tensor) -> Tensor:
        """(R, 2) the step turned as little as it must be for its segment to be free and its
        end `margin` outside (its length kept if it can be, else shortened), so the path turns
        along the zone's side and goes on; the pulled-back point where no turn is free. Nearest
        to the waypoint would park the path on the zone's face, from where no straight segment
        gets around."""
        area = area.select_rows(rows)
        if hasattr(area, "at"):  # a forecast: each row's segment at its waypoint's moment
            area = area.at(cols)
        begin = seg_start.to(torch.float64)
        step = seg_end.to(torch.float64) - begin
        turned = torch.einsum("kij,rj->rki", _TURNS.to(step), step)  # (R, K, 2)
        candidates = begin[:, None] + turned
        starts = begin[:, None].expand_as(candidates)
        free = (area.segment_clear_fraction(starts, candidates) >= 1.0) \
            & (area.signed_distance(candidates) >= self.margin)
        first = free.float().argmax(dim=1)  # _TURNS runs from the least turn to the most
        chosen = candidates[torch.arange(len(rows)), first]
        return torch.where(free.any(dim=1)[:, None], chosen, pulled_back.to(torch.float64))


def _turns() -> Tensor:
    """(K, 2, 2) rotations, each scaled by 1, 3/4 or 1/2, ordered by how far they turn (either
    way), the longest first at each angle (`PathRepair`)."""
    degrees = [sign * a for a in range(10, 160, 10) for sign in (1, -1)]
    matrices = []
    for angle in degrees:
        c, s = math.cos(math.radians(angle)), math.sin(math.radians(angle))
        for scale in (1.0, 0.75, 0.5):
            matrices.append(scale * torch.tensor([[c, -s], [s, c]], dtype=torch.float64))
    return torch.stack(matrices)


_TURNS = _turns()


@dataclass
class Until:
    """Runs `hook` only while the loop's progress is at most `last`: guidance stopped for the
    last updates, so they can bring the sample back toward what the policy learned (as ITPS
    found helpful); the final projection and path repair still have the last word."""

    hook: SampleHook
    last: float

    def __call__(self, sample: Tensor, step: DenoisingStep) -> Tensor:
        return self.hook(sample, step) if step.progress <= self.last + 1e-9 else sample


@dataclass
class ShrinkingMargin:
    """Runs a guidance hook (one with an `area`) on its area grown by `extra` px at the first
    update, the growth shrinking linearly to none at the last: noisy early samples are kept
    further out, the final ones only as far as needed. Whole pixels, so a loop builds at most
    `extra` + 1 derived areas, each cached by the area."""

    hook: Resampling | GradientPush | ResamplingThenPush
    extra: float

    def __call__(self, sample: Tensor, step: DenoisingStep) -> Tensor:
        grow = round(self.extra * (1.0 - step.progress))
        area = self.hook.area.inflate(float(grow)) if grow > 0 else self.hook.area
        return replace(self.hook, area=area)(sample, step)


@dataclass
class CommittedPrefix:
    """Real-time chunking by inpainting: the first waypoints of the chunk being denoised are
    the ones that will already have executed (or been committed) when it arrives, so they are
    held to `known` after every update, noised to the level the sample has reached (one fixed
    noise draw), and set clean after the last. `weights` (K,) or per row (B, K), in [0, 1], give
    1 to the committed waypoints and less to the ones after, which are only drawn toward
    `known` (the rest of the chunk in force), so the handover does not jump; a row of zeros
    leaves that row free. Run it before the constraint hooks: a committed waypoint is skipped
    when the chunk is installed, so the constraints may move it, and they keep the soft ones
    after it out of the zones."""

    known: Tensor  # (B, K, 2) workspace px, aligned with the chunk's first K waypoints
    weights: Tensor  # (K,) or (B, K)

    def __post_init__(self) -> None:
        if self.weights.shape not in (self.known.shape[1:2], self.known.shape[:2]):
            raise ValueError(f"weights {tuple(self.weights.shape)} must match the known "
                             f"waypoints {tuple(self.known.shape[:2])}")
        # Known waypoints, their noise, weights and 1 - weights in the sample's dtype: the
        # noise drawn at the first update, and none of them changing from step to step.
        self._held: tuple[Tensor, Tensor, Tensor, Tensor] | None = None

    def repeated(self, times: int) -> CommittedPrefix:
        """The same prefix for `times` candidates of each row, rows kept together."""
        weights = self.weights if self.weights.dim() == 1 else \
            self.weights.repeat_interleave(times, dim=0)
        return CommittedPrefix(self.known.repeat_interleave(times, dim=0), weights)

    def __call__(self, sample: Tensor, step: DenoisingStep) -> Tensor:
        if self._held is None:
            w = self.weights.to(sample)
            w = (w if w.dim() == 2 else w[None])[..., None]
            noise = torch.randn(self.known.shape, generator=step.generator).to(sample)
            self._held = self.known.to(sample), noise, w, 1.0 - w
        known, noise, w, rest = self._held
        out = sample.clone()
        out[:, :known.shape[1]] = w * step.noised(known, noise) + rest * sample[:, :known.shape[1]]
        return out


@dataclass
class LastUpdate:
    """Keeps the sample as the last update left it, before the hooks after this one: what
    they changed can then be measured (candidate selection)."""

    sample: Tensor | None = None

    def __call__(self, sample: Tensor, step: DenoisingStep) -> Tensor:
        if step.index == step.total - 1:
            self.sample = sample.clone()
        return sample


def prefix_weights(committed: int, soft: int) -> Tensor:
    """1 for the committed waypoints, then `soft` weights falling linearly toward 0."""
    falling = torch.arange(soft, 0, -1, dtype=torch.float64) / (soft + 1)
    return torch.cat([torch.ones(committed, dtype=torch.float64), falling])


@dataclass
class OnRows:
    """Runs `hook` on some rows of the batch only: configurations that share a sampler share
    its network calls, each with its own hooks on its own episodes."""

    hook: SampleHook
    rows: Tensor  # (R,) row indices

    def __call__(self, sample: Tensor, step: DenoisingStep) -> Tensor:
        out = sample.clone()
        out[self.rows] = self.hook(sample[self.rows], step)
        return out
