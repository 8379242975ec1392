"""The batched vehicle state: E environments x V vehicle slots, vehicle 0 of each the ego."""

from __future__ import annotations

import math
from typing import NamedTuple, Optional, Union

import torch

from mmpc.sim.config import SimConfig

Number = Union[float, torch.Tensor]

#: Floating-point fields of :class:`VehicleState` of shape (E, V).
FLOAT_FIELDS = ("x", "y", "heading", "speed", "length", "width", "target_speed", "idm_delta")
#: Integer (lane) fields, int64 (E, V).
LANE_FIELDS = ("lane", "target_lane")
#: Boolean fields (E, V).
FLAG_FIELDS = ("alive", "crashed", "impact_pending", "lane_change_enabled", "check_collisions")
#: Fields kept in float64 whatever the state's dtype, (E, V).
DOUBLE_FIELDS = ("lane_change_timer",)


class VehicleState(NamedTuple):
    """Every vehicle of E environments; slot 0 is the ego, slots 1.. the IDM vehicles, in
    highway-env's ``road.vehicles`` order (which decides the order collisions are handled in).

    Shapes: every field (E, V) except ``impact`` (E, V, 2).

    ``lane_change_timer`` is float64 in a float32 state too: MOBIL runs when it exceeds
    ``SimConfig.lane_change_delay``, and ten float32 additions of 0.1 s exceed 1 s one frame
    earlier than highway-env's float64 ones.
    """

    x: torch.Tensor  # (E, V) float, position along the road [m]
    y: torch.Tensor  # (E, V) float, lateral position, lane k's centre at k * lane_width [m]
    heading: torch.Tensor  # (E, V) float, body heading from +x [rad]
    speed: torch.Tensor  # (E, V) float [m/s]
    length: torch.Tensor  # (E, V) float, body length, also the bicycle's wheelbase [m]
    width: torch.Tensor  # (E, V) float [m]
    lane: torch.Tensor  # (E, V) int64, nearest lane (highway-env's ``lane_index``), updated every frame
    target_lane: torch.Tensor  # (E, V) int64, the lane an IDM vehicle steers to
    target_speed: torch.Tensor  # (E, V) float, IDM desired speed [m/s]
    idm_delta: torch.Tensor  # (E, V) float, IDM speed exponent (highway-env draws it in [3.5, 4.5])
    alive: torch.Tensor  # (E, V) bool, the slot holds a vehicle (False: padding, never moves nor collides)
    crashed: torch.Tensor  # (E, V) bool, crashed vehicles brake to rest with straight wheels
    impact: torch.Tensor  # (E, V, 2) float, push [m] from a predicted collision, applied at the next frame
    impact_pending: torch.Tensor  # (E, V) bool, ``impact`` is to be applied (highway-env's ``impact is not None``)
    lane_change_enabled: torch.Tensor  # (E, V) bool, the vehicle may change lane by MOBIL (highway-env's ``enable_lane_change``)
    lane_change_timer: torch.Tensor  # (E, V) float64, time since the last MOBIL evaluation (highway-env's ``timer``) [s]
    check_collisions: torch.Tensor  # (E, V) bool, pairs are tested when either vehicle checks (highway-env's ``check_collisions``)

    @property
    def shape(self) -> tuple[int, int]:
        """(E, V)."""
        return tuple(self.x.shape)


def lane_of(y: torch.Tensor, config: SimConfig) -> torch.Tensor:
    """Nearest lane of lateral positions ``y`` [m] (int64, same shape); a position halfway between
    two lanes belongs to the lower index, as highway-env's ``get_closest_lane_index`` decides."""
    index = torch.ceil((y - 0.5 * config.lane_width) / config.lane_width)
    return index.clamp(0, config.lanes - 1).to(torch.int64)


def on_road(y: torch.Tensor, config: SimConfig) -> torch.Tensor:
    """Whether lateral positions ``y`` [m] lie on their nearest lane (bool, same shape):
    highway-env's ``on_road`` on a straight road, within half a lane width of its centre."""
    return (y - lane_of(y, config).to(y.dtype) * config.lane_width).abs() <= 0.5 * config.lane_width


def vehicle_state(
    x: torch.Tensor,
    y: torch.Tensor,
    heading: Number = 0.0,
    speed: Number = 0.0,
    *,
    config: SimConfig = SimConfig(),
    length: Number = 5.0,
    width: Number = 2.0,
    target_lane: Optional[torch.Tensor] = None,
    target_speed: Optional[Number] = None,
    idm_delta: Number = 4.0,
    alive: Optional[torch.Tensor] = None,
    lane_change_enabled: Union[bool, torch.Tensor] = True,
    lane_change_timer: Optional[torch.Tensor] = None,
    check_collisions: Union[bool, torch.Tensor] = True,
) -> VehicleState:
    """Build a validated state; ``x`` decides E, V, dtype and device, numbers and tensors broadcast.

    Args:
        x, y: (E, V) positions [m], floating point; slot 0 of each environment is the ego.
        heading: [rad]. speed: [m/s]. length, width: [m] (highway-env's 5 x 2 by default).
        target_lane: int (E, V); default: each vehicle's nearest lane.
        target_speed: [m/s]; default: the initial speed (highway-env's ``ControlledVehicle``).
        idm_delta: IDM exponent (highway-env's class value 4).
        alive: bool (E, V); default: all present.
        lane_change_enabled: bool (E, V), whether each IDM vehicle may change lane by MOBIL
            (highway-env's default: yes); slot 0, the ego, never decides by MOBIL.
        lane_change_timer: (E, V) seconds since each vehicle's last MOBIL evaluation, cast to
            float64; default: highway-env's creation value ``(x + y) * pi mod lane_change_delay``
            (a function of the initial position, not a random draw).

    Example:
        >>> state = vehicle_state(torch.tensor([[0.0, 30.0]]), torch.tensor([[4.0, 4.0]]), speed=20.0)
        >>> state.shape, state.lane.tolist()
        ((1, 2), [[1, 1]])
    """
    if not isinstance(x, torch.Tensor) or x.dim() != 2 or not x.is_floating_point():
        got = f"{tuple(x.shape)} {x.dtype}" if isinstance(x, torch.Tensor) else type(x).__name__
        raise ValueError(f"`x` must be a floating-point tensor of shape (E, V); got {got}")

    def full(name: str, value, dtype: torch.dtype) -> torch.Tensor:
        if isinstance(value, torch.Tensor):
            if value.device != x.device:
                raise ValueError(f"`{name}` is on {value.device}; `x` is on {x.device}")
            fits = value.dim() <= 2 and all(a in (1, b) for a, b in zip(value.shape[::-1], x.shape[::-1]))
            if not fits:
                raise ValueError(f"`{name}` must broadcast to (E, V) = {tuple(x.shape)}; got {tuple(value.shape)}")
            return value.to(dtype).expand(x.shape).clone()
        return torch.full(x.shape, value, dtype=dtype, device=x.device)

    y = full("y", y, x.dtype)
    speed = full("speed", speed, x.dtype)
    lane = lane_of(y, config)
    state = VehicleState(
        x=x.clone(),
        y=y,
        heading=full("heading", heading, x.dtype),
        speed=speed,
        length=full("length", length, x.dtype),
        width=full("width", width, x.dtype),
        lane=lane,
        target_lane=lane.clone() if target_lane is None else full("target_lane", target_lane, torch.int64),
        target_speed=speed.clone() if target_speed is None else full("target_speed", target_speed, x.dtype),
        idm_delta=full("idm_delta", idm_delta, x.dtype),
        alive=torch.ones(x.shape, dtype=torch.bool, device=x.device) if alive is None else full("alive", alive, torch.bool),
        crashed=torch.zeros(x.shape, dtype=torch.bool, device=x.device),
        impact=torch.zeros((*x.shape, 2), dtype=x.dtype, device=x.device),
        impact_pending=torch.zeros(x.shape, dtype=torch.bool, device=x.device),
        lane_change_enabled=full("lane_change_enabled", lane_change_enabled, torch.bool),
        lane_change_timer=(torch.remainder((x.double() + y.double()) * math.pi, config.lane_change_delay)
                           if lane_change_timer is None else full("lane_change_timer", lane_change_timer, torch.float64)),
        check_collisions=full("check_collisions", check_collisions, torch.bool),
    )
    check_state(state, config)
    return state


def check_state(state: VehicleState, config: SimConfig) -> None:
    """Raise ``ValueError`` naming the field unless ``state`` is consistent: one (E, V) shape,
    one float dtype (float64 timers) and one device, int64 lanes within the road, bool flags, finite numbers
    and positive sizes. Reads the values (a host synchronisation)."""
    if not isinstance(state, VehicleState):
        raise ValueError(f"`state` must be a VehicleState; got {type(state).__name__}")
    shape, dtype, device = tuple(state.x.shape), state.x.dtype, state.x.device
    if len(shape) != 2 or shape[1] < 1:
        raise ValueError(f"`state.x` must have shape (E, V) with V >= 1 (the ego); got {shape}")
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"`state.x` must be float32 or float64; got {dtype}")
    expected = {name: dtype for name in FLOAT_FIELDS}
    expected.update({name: torch.int64 for name in LANE_FIELDS})
    expected.update({name: torch.bool for name in FLAG_FIELDS})
    expected.update({name: torch.float64 for name in DOUBLE_FIELDS})
    expected["impact"] = dtype
    for name, field_dtype in expected.items():
        value = getattr(state, name)
        field_shape = (*shape, 2) if name == "impact" else shape
        if tuple(value.shape) != field_shape:
            raise ValueError(f"`state.{name}` must have shape {field_shape} like `state.x`; got {tuple(value.shape)}")
        if value.dtype != field_dtype:
            raise ValueError(f"`state.{name}` must be {field_dtype}; got {value.dtype}")
        if value.device != device:
            raise ValueError(f"`state.{name}` is on {value.device}; `state.x` is on {device}")
        if field_dtype.is_floating_point and not bool(torch.isfinite(value).all()):
            bad = torch.nonzero(~torch.isfinite(value))[:3, 0].tolist()
            raise ValueError(f"`state.{name}` holds NaN or inf (environments {bad}...)")
    for name in LANE_FIELDS:
        value = getattr(state, name)
        if bool(((value < 0) | (value >= config.lanes)).any()):
            raise ValueError(f"`state.{name}` must lie in [0, {config.lanes - 1}] (SimConfig.lanes = {config.lanes}); "
                             f"got values in [{int(value.min())}, {int(value.max())}]")
    for name in ("length", "width"):
        if not bool((getattr(state, name) > 0).all()):
            raise ValueError(f"`state.{name}` must be > 0 m everywhere; got min {float(getattr(state, name).min())}")
