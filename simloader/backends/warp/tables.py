"""What a Warp engine gathers from per batch, put on its device once: the per-model tables
every engine starts trajectories from (`SimConfig.model_tables`), the generators' parameters,
and where each state component and control input sits in a row (`simloader.layout`)."""

from __future__ import annotations

from typing import Any

import mujoco
import torch

from simloader import layout

S = mujoco.mjtState
# mjSTATE_INTEGRATION components and the MuJoCo Warp data arrays that hold them
STATE_ARRAYS = {S.mjSTATE_TIME: "time", S.mjSTATE_QPOS: "qpos", S.mjSTATE_QVEL: "qvel",
                S.mjSTATE_ACT: "act", S.mjSTATE_WARMSTART: "qacc_warmstart",
                S.mjSTATE_CTRL: "ctrl", S.mjSTATE_QFRC_APPLIED: "qfrc_applied",
                S.mjSTATE_XFRC_APPLIED: "xfrc_applied", S.mjSTATE_EQ_ACTIVE: "eq_active",
                S.mjSTATE_MOCAP_POS: "mocap_pos", S.mjSTATE_MOCAP_QUAT: "mocap_quat",
                S.mjSTATE_USERDATA: "userdata"}


class DeviceTables:
    """Per-model host tables on the device, (nmodels, ...) each, gathered per batch by each
    trajectory's model: reset rows (mjSTATE_INTEGRATION as mj_resetData leaves them), undriven
    control columns, clamp bounds, and with variants the initial states from the model. Also
    the row layouts the engine reads and writes MuJoCo Warp's arrays by.

    Attributes (besides the tables):
      physics_cols: the mjSTATE_FULLPHYSICS columns of an mjSTATE_INTEGRATION row.
      integration: (data array, first column, end) of each non-empty mjSTATE_INTEGRATION
        component, in mjtState order (a batch's reset and checkpoint).
      inputs: (columns of a control row, data array, boolean) of each control input.
      control_params, noise_params: the control generators' and the policy noise's
        parameters, for draws on the device.
      clamped: (nu,) bool, the actuators MuJoCo clamps.
    """

    def __init__(self, config: Any, device: torch.device):
        c = config
        f32 = dict(dtype=torch.float32, device=device)
        tables = c.model_tables(layout.INTEGRATION)
        self.reset_rows = torch.as_tensor(tables.reset_rows, **f32)
        self.control_defaults = torch.as_tensor(tables.control_defaults, **f32)
        self.low, self.high = (torch.as_tensor(b, **f32) for b in (tables.low, tables.high))
        self.variant_states = (None if tables.variant_states is None else
                               torch.as_tensor(tables.variant_states, **f32))
        self.control_params = c.control.torch_params(self.reset_rows)
        self.noise_params = (c.policy_noise.torch_params(self.reset_rows)
                             if c.policy_noise is not None else [])
        self.clamped = torch.as_tensor(c.model.actuator_ctrllimited.astype(bool), device=device)
        self.physics_cols = torch.as_tensor(layout.component_columns(
            c.model, layout.INTEGRATION, layout.FULLPHYSICS), device=device)
        self.integration = []
        for bit, name in sorted(STATE_ARRAYS.items(), key=lambda item: int(item[0])):
            cols = layout.component_columns(c.model, layout.INTEGRATION, int(bit))
            if len(cols):
                self.integration.append((name, int(cols[0]), int(cols[-1]) + 1))
        self.inputs = [(comp.columns, comp.name, comp.name == "eq_active")
                       for comp in layout.control_layout(c.model, c.control_spec)]
