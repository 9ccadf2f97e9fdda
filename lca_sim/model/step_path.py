"""One model step's path: eq. (2)'s rigid-body terms, their hold, and the kernel call.

`StepPath` is the part of `lca_sim.model.simulator.Simulator` that owns how a step reaches the
compiled code: A(q) and C(q, qdot) qdot + Q(q) evaluated at every step (the exact scheme, one
compiled call on a frame of raw addresses) or once per hold of k steps at the hold's mean
position. Why the frame: docs/model.md, "The exact step's call path".
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

from lca_sim.errors import LcaHilError
from lca_sim.model import kernel
from lca_sim.model.gantry import Gantry

FloatArray = npt.NDArray[np.float64]


class StaleCodeError(LcaHilError):
    """A compiled drive came from numba's cache of other code than the running (`code_version`).

    It took no step. Its owner recompiles it from the running code and calls again.
    """


class StepPath:
    """The rigid-body terms and the kernel step on a simulator's `work` and `model` arrays.

    Args:
        gantry: the rigid-body model; its scratch buffers are used in place.
        work: the simulator's state and signals (rows `kernel.X_*`), updated in place.
        model: the packed constants (`kernel.pack_model`), read at every step.
        dt_s: the fixed step, s.
        hold_steps: steps per evaluation of the rigid-body terms (1: at every step).
    """

    def __init__(
        self, gantry: Gantry, work: FloatArray, model: FloatArray, dt_s: float, hold_steps: int
    ) -> None:
        self._gantry = gantry
        self._work, self._model, self._dt_s = work, model, dt_s
        # Views into the work array, made once: the hot path only indexes them.
        self._position = work[kernel.X_POSITION]
        self._velocity = work[kernel.X_VELOCITY]
        self._dynamics = gantry.terms_in_place
        n = len(self._position)
        # The held terms: the gantry's buffers themselves when evaluated at every step,
        # copies when held (another evaluation would overwrite its buffers).
        self.hold_steps = hold_steps
        self._hold_lead_s = 0.5 * (hold_steps - 1) * dt_s
        self._hold_position = np.zeros(n)
        self._held_mass = np.zeros((n, n))
        self._held_nle = np.zeros(n)
        self._terms: tuple[FloatArray, FloatArray] = (self._held_mass, self._held_nle)
        self._age = 0  # steps taken on the held terms; 0: evaluate before the next step
        self._term_buffers = gantry.term_buffers()  # mass, nle, tree, body: fixed for life
        self._fused_out = np.zeros(2, dtype=np.int64)  # a fused advance's (steps, age)
        self.step: Callable[[FloatArray], int] = self._bind()
        """One step under a float64 voltage array of the right shape; `kernel.OK` or why not."""

    def restart(self) -> None:
        """Start a new hold: the next step evaluates the terms at the state then."""
        self._age = 0

    def evaluate(self, command: FloatArray) -> None:
        """Fill the signals for the state in `work` without advancing (a zero-length step)."""
        mass, nle = self._dynamics(self._position, self._velocity)
        kernel.step(mass, nle, command, self._work, self._model, 0.0)

    def advance_with(
        self,
        n_steps: int,
        stepper: Callable[..., int],
        volts: FloatArray,
        *args: FloatArray | int,
    ) -> tuple[int, bool]:
        """Up to `n_steps` of a compiled drive, one call per hold; (steps done, all done).

        See `Simulator.advance_with` for `stepper`'s signature.

        Raises:
            StaleCodeError: the stepper returned -1 (compiled against other code than the
                running, nothing touched); its owner recompiles it and calls again.
        """
        work, model, dt_s = self._work, self._model, self._dt_s
        hold = self.hold_steps
        total, left = 0, n_steps
        while left > 0:
            mass, nle = self._rigid_body_terms()
            chunk = min(hold - self._age, left)
            done = stepper(chunk, volts, *args, mass, nle, work, model, dt_s)
            if done < 0:  # nothing touched; the held terms are evaluated again alike
                raise StaleCodeError(f"{stepper} was compiled against other code")
            total += done
            self._age = (self._age + done) % hold
            left -= done
            if done < chunk:
                return total, False
        return total, True

    def advance_fused(
        self, n_steps: int, fused: Any, volts: FloatArray, *args: FloatArray | int
    ) -> tuple[int, bool]:
        """`advance_with` in one compiled call that evaluates the held terms itself.

        Held terms only (`hold_steps` > 1). `fused(n_steps, age, hold, lead_s, hold_position,
        held_mass, held_nle, mass, nle, tree, body, volts, *args, work, model, dt_s, out)` is a
        numba function (`commanded_plant._current_loops_held`) that does what `advance_with`
        does with its stepper, the same bits, and returns 1 (all steps), 0 (a step refused its
        voltages) or -1 (compiled against other code than the running: nothing touched).

        Raises:
            StaleCodeError: `fused` returned -1; its owner recompiles it and calls again.
        """
        mass, nle, tree, body = self._term_buffers
        out = self._fused_out
        verdict: int = fused(
            n_steps,
            self._age,
            self.hold_steps,
            self._hold_lead_s,
            self._hold_position,
            self._held_mass,
            self._held_nle,
            mass,
            nle,
            tree,
            body,
            volts,
            *args,
            self._work,
            self._model,
            self._dt_s,
            out,
        )
        if verdict < 0:
            raise StaleCodeError(f"{fused} was compiled against other code")
        self._age = int(out[1])
        return int(out[0]), verdict == 1

    def _rigid_body_terms(self) -> tuple[FloatArray, FloatArray]:
        """A(q) and C(q, qdot) qdot + Q(q) for the next step: evaluated, or still held."""
        if self._age == 0:
            if self.hold_steps == 1:
                self._terms = self._dynamics(self._position, self._velocity)
            else:
                q = self._hold_position
                np.multiply(self._velocity, self._hold_lead_s, out=q)
                q += self._position
                mass, nle = self._dynamics(q, self._velocity)
                self._held_mass[:] = mass
                self._held_nle[:] = nle
                self._terms = (self._held_mass, self._held_nle)
        return self._terms

    def _held_step(self, command: FloatArray) -> int:
        """One kernel step on the held rigid-body terms (evaluated when a new hold starts)."""
        mass, nle = self._rigid_body_terms()
        code: int = kernel.step(mass, nle, command, self._work, self._model, self._dt_s)
        if code == kernel.OK:
            self._age = (self._age + 1) % self.hold_steps
        return code

    def _bind(self) -> Callable[[FloatArray], int]:
        """The rigid-body terms and `kernel.step` of one step, as one call on a voltage array.

        At 4 axes a step's cost is mostly the calls around the arithmetic, so the exact scheme
        is one compiled call, `kernel.step_in_frame`, on a frame of the addresses of everything
        fixed for the simulator's life: `work`, `model` and the gantry's compiled terms' tree,
        scratch and output buffers. It computes what the general path computes
        (`Gantry.terms_in_place`, then `kernel.step`), so the same bits.
        """
        if self.hold_steps > 1:
            return self._held_step
        work, model, dt_s = self._work, self._model, self._dt_s
        terms_in_place = self._gantry.terms_in_place
        position, velocity = self._position, self._velocity
        frame = self._frame()
        if frame is None:
            kernel_step = kernel.step

            def exact_kernel_step(command: FloatArray) -> int:
                mass, nle = terms_in_place(position, velocity)
                code: int = kernel_step(mass, nle, command, work, model, dt_s)
                return code

            return exact_kernel_step
        frame_address = int(frame.ctypes.data)  # `frame` is kept in `_frame_arrays`
        # A dry run on the zero state (the simulator resets after): the compiled step may come
        # from numba's cache of an older rigid_body (kernel.STALE_CODE), then it is compiled again.
        zero_volts = np.zeros(len(position))
        if kernel.step_in_frame_entry()(zero_volts, frame_address, 0.0) == kernel.STALE_CODE:
            kernel.recompile_step_in_frame()
            if kernel.step_in_frame_entry()(zero_volts, frame_address, 0.0) != kernel.OK:
                raise RuntimeError("kernel.step_in_frame does not run the loaded rigid_body")
        step_in_frame = kernel.step_in_frame_entry()  # the caller checks the voltages' type

        def exact_frame_step(command: FloatArray) -> int:
            code: int = step_in_frame(command, frame_address, dt_s)
            return code

        return exact_frame_step

    def _frame(self) -> npt.NDArray[np.int64] | None:
        """`kernel.step_in_frame`'s frame, or None when numba's JIT is off (no raw addresses)."""
        if not kernel.FRAME_AVAILABLE:
            return None
        mass, nle, tree, body = self._gantry.term_buffers()
        frame = kernel.make_frame(mass, nle, self._work, self._model, tree, body)
        self._frame_arrays = (frame, mass, nle, tree, body)  # keeps the frame's memory alive
        return frame
