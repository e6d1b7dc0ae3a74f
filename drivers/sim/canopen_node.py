"""A simulated CANopen device (CiA 301 slave) on a :class:`~drivers.motor.port.CanPort`.

The server half of what :mod:`drivers.motor` is the client of: an object dictionary, an
expedited SDO server with the standard abort codes, NMT, boot-up and heartbeat producer, a
heartbeat consumer with the error behaviour of 0x1029, TPDOs sent by event timer and RPDOs acted
on at reception, both in OPERATIONAL only. Everything is timed with the event loop (one cycle
task), so it runs unchanged in real and virtual time. A device profile (the CiA 402 drive)
subclasses it and overrides the hooks.

NMT state changes and heartbeat losses are logged with ``mono_s`` (``time.monotonic()``, the
same clock in every process of the machine) so a benchmark can time the host's stalls against
the device's reactions.
"""

from __future__ import annotations

import asyncio
import struct
import time
from collections.abc import Coroutine
from dataclasses import dataclass
from typing import Any

import can
import structlog

from drivers.motor import emcy, nmt, pdo, sdo, sdo_aborts
from drivers.motor.errors import CanBusError
from drivers.motor.port import CanPort

log = structlog.get_logger(__name__)

_COMMUNICATION_REGISTER = 0x11  # error register 0x1001: generic error + communication error
_RPDO_TRANSMISSION_TYPES = (0xFE, 0xFF)  # event driven: acted on at reception (no SYNC served)


def monotonic_s() -> float:
    """The machine's monotonic clock (s), stamped into the simulator's logs so another process
    can compare its own stamps with them."""
    return time.monotonic()


@dataclass
class ObjectEntry:
    """One object dictionary entry: struct format, value and access."""

    fmt: str
    value: int = 0
    writable: bool = True
    readable: bool = True
    mappable: bool = False

    @property
    def size(self) -> int:
        return struct.calcsize(self.fmt)


class SdoAbortRequest(Exception):
    """Raised by a write hook to abort the SDO transfer with ``code``."""

    def __init__(self, code: int) -> None:
        self.code = code
        super().__init__(f"SDO abort 0x{code:08X}")


class SimulatedNode:
    """A CANopen slave.

    Fault injection: ``sdo_delay_s`` (answer SDO requests late), ``drop_sdo_replies(n)``,
    ``drop_tpdos(n)``, ``stop_heartbeat()`` / ``resume_heartbeat()``, ``disconnect()`` /
    ``reconnect()`` (the node falls silent and deaf, like a pulled cable), ``reboot()``.
    Observed: ``emcy_sent`` (every EMCY error sent), ``rpdo_length_errors`` (RPDOs ignored for
    their length, each answered with EMCY 0x8210), ``rpdo_values_refused``.
    """

    TICK_S = 0.005
    TPDO_COUNT = 4
    RPDO_COUNT = 4
    DEVICE_TYPE = 0
    IDENTITY = (0x0000_0000, 0, 0, 0)  # 0x1018: vendor id, product code, revision, serial number
    DEFAULT_TPDO_MAPPING: dict[int, tuple[int, ...]] = {}  # TPDO k+1 -> power-on mapping entries
    DEFAULT_RPDO_MAPPING: dict[int, tuple[int, ...]] = {}  # RPDO k+1 -> power-on mapping entries

    def __init__(self, port: CanPort, node_id: int, *, name: str = "node") -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f"node id {node_id} outside 1..127")
        self.port = port
        self.node_id = node_id
        self.name = name
        self.nmt_state = nmt.NmtState.BOOT_UP
        self.od: dict[tuple[int, int], ObjectEntry] = {}
        self.sdo_delay_s = 0.0
        self.heartbeat_enabled = True
        self.silent = False
        self.frames_sent = 0
        self.emcy_sent: list[emcy.Emcy] = []
        self.rpdo_length_errors = 0
        self.rpdo_values_refused = 0
        self._drop_sdo = 0
        self._drop_tpdo = 0
        self._consumer_seen: dict[int, float] = {}
        self._consumer_lost: set[int] = set()
        self._tpdo_due: dict[int, tuple[float, float]] = {}
        self._heartbeat_due: float | None = None
        self._mapping_cache: dict[int, tuple[pdo.MappedObject, ...]] = {}
        self._tasks: set[asyncio.Task[None]] = set()
        self.reset_communication_objects()

    # ------------------------------------------------------------------ object dictionary

    def reset_communication_objects(self) -> None:
        """Communication objects (0x1000-0x1FFF) to their power-on values."""
        n = self.node_id
        self.od.update(
            {
                (0x1000, 0): ObjectEntry("<I", self.DEVICE_TYPE, writable=False),
                (0x1001, 0): ObjectEntry("<B", 0, writable=False, mappable=True),
                (0x1014, 0): ObjectEntry("<I", nmt.emcy_cob_id(n)),  # EMCY COB-ID, bit 31: no EMCY
                (0x1016, 0): ObjectEntry("<B", 1, writable=False),
                (0x1016, 1): ObjectEntry("<I", 0),
                (0x1017, 0): ObjectEntry("<H", 0),
                (0x1018, 0): ObjectEntry("<B", 4, writable=False),
                **{(0x1018, sub + 1): ObjectEntry("<I", value, writable=False)
                   for sub, value in enumerate(self.IDENTITY)},
                (0x1029, 0): ObjectEntry("<B", 1, writable=False),
                (0x1029, 1): ObjectEntry("<B", nmt.CommunicationErrorBehaviour.PRE_OPERATIONAL),
            }
        )
        for k in range(self.TPDO_COUNT):
            comm = pdo.TPDO_COMMUNICATION + k
            self.od.update(
                {
                    (comm, 0): ObjectEntry("<B", 5, writable=False),
                    (comm, 1): ObjectEntry("<I", (0 if k == 0 else pdo.COB_ID_INVALID) | nmt.tpdo_cob_id(k + 1, n)),
                    (comm, 2): ObjectEntry("<B", pdo.TRANSMISSION_EVENT_DRIVEN),
                    (comm, 3): ObjectEntry("<H", 0),
                    (comm, 5): ObjectEntry("<H", 0),
                }
            )
            self._reset_mapping(pdo.TPDO_MAPPING + k, self.DEFAULT_TPDO_MAPPING.get(k, ()))
        for k in range(self.RPDO_COUNT):
            comm = pdo.RPDO_COMMUNICATION + k
            entries = self.DEFAULT_RPDO_MAPPING.get(k, ())
            self.od.update(
                {
                    (comm, 0): ObjectEntry("<B", 2, writable=False),
                    (comm, 1): ObjectEntry("<I", (0 if entries else pdo.COB_ID_INVALID) | nmt.rpdo_cob_id(k + 1, n)),
                    (comm, 2): ObjectEntry("<B", pdo.TRANSMISSION_EVENT_DRIVEN),
                }
            )
            self._reset_mapping(pdo.RPDO_MAPPING + k, entries)
        self._tpdo_due.clear()
        self._consumer_seen.clear()
        self._consumer_lost.clear()
        self._mapping_cache.clear()

    def _reset_mapping(self, index: int, entries: tuple[int, ...]) -> None:
        self.od[(index, 0)] = ObjectEntry("<B", len(entries))
        for sub in range(1, 9):
            self.od[(index, sub)] = ObjectEntry("<I", entries[sub - 1] if sub <= len(entries) else 0)

    def value(self, index: int, subindex: int = 0) -> int:
        """An object's current value (live objects come from :meth:`read_object`)."""
        return self.read_object(index, subindex)

    def read_object(self, index: int, subindex: int) -> int:
        """Hook: the value of an object; live values (statusword, position) override this."""
        return self.od[(index, subindex)].value

    def write_object(self, index: int, subindex: int, value: int) -> None:
        """Hook: store a written value, enforcing the PDO rules of CiA 301 and 0x1029's range.

        Raises:
            SdoAbortRequest: the write is refused (code says why).
        """
        parameters = self._pdo_parameters(index)
        if parameters is not None and parameters[0] == index:  # a mapping parameter
            self._check_mapping_write(parameters[1], index, subindex, value)
            self._mapping_cache.pop(index, None)
        elif parameters is not None:  # a communication parameter
            self._check_communication_write(index, subindex, value)
        elif index == 0x1029 and value not in tuple(nmt.CommunicationErrorBehaviour):
            raise SdoAbortRequest(sdo_aborts.ABORT_VALUE_RANGE)
        self.od[(index, subindex)].value = value

    def receive_write(self, index: int, subindex: int, value: int, transport: str) -> None:
        """Hook: a value written from the bus (``transport`` ``sdo`` or ``rpdo``); both arrive
        through :meth:`write_object`, so an object acts the same whichever carried it."""
        self.write_object(index, subindex, value)

    def _pdo_parameters(self, index: int) -> tuple[int, int] | None:
        """(mapping, communication) parameter indices of the PDO whose mapping or communication
        parameter ``index`` is (None: neither)."""
        for mapping, comm, count in ((pdo.TPDO_MAPPING, pdo.TPDO_COMMUNICATION, self.TPDO_COUNT),
                                     (pdo.RPDO_MAPPING, pdo.RPDO_COMMUNICATION, self.RPDO_COUNT)):
            for first in (mapping, comm):
                if first <= index < first + count:
                    return mapping + index - first, comm + index - first
        return None

    def _check_communication_write(self, index: int, subindex: int, value: int) -> None:
        current = self.od[(index, subindex)].value
        if subindex == 1 and not (current | value) & pdo.COB_ID_INVALID and (current ^ value) & 0x1FFF_FFFF:
            raise SdoAbortRequest(sdo_aborts.ABORT_VALUE_RANGE)  # a valid PDO's COB-ID changes only via invalid
        receive = index < pdo.TPDO_COMMUNICATION
        if receive and subindex == 2 and value not in _RPDO_TRANSMISSION_TYPES:
            raise SdoAbortRequest(sdo_aborts.ABORT_VALUE_RANGE)

    def _check_mapping_write(self, comm_index: int, index: int, subindex: int, value: int) -> None:
        if not self.od[(comm_index, 1)].value & pdo.COB_ID_INVALID:
            raise SdoAbortRequest(sdo_aborts.ABORT_DEVICE_STATE)
        if subindex == 0:
            if value > 8:
                raise SdoAbortRequest(sdo_aborts.ABORT_VALUE_RANGE)
            bits = sum(pdo.parse_map_entry(self.od[(index, s)].value)[2] for s in range(1, value + 1))
            if bits > 64:
                raise SdoAbortRequest(sdo_aborts.ABORT_PDO_LENGTH)
            return
        if self.od[(index, 0)].value != 0:
            raise SdoAbortRequest(sdo_aborts.ABORT_UNSUPPORTED_ACCESS)
        obj_index, obj_sub, bits = pdo.parse_map_entry(value)
        entry = self.od.get((obj_index, obj_sub))
        receive = comm_index < pdo.TPDO_COMMUNICATION  # an RPDO writes what it maps
        if entry is None or not entry.mappable or entry.size * 8 != bits or (receive and not entry.writable):
            raise SdoAbortRequest(sdo_aborts.ABORT_NOT_MAPPABLE)

    def tpdo_mapping(self, k: int) -> tuple[pdo.MappedObject, ...]:
        """The current mapping of TPDO k+1."""
        return self._mapping(pdo.TPDO_MAPPING + k)

    def rpdo_mapping(self, k: int) -> tuple[pdo.MappedObject, ...]:
        """The current mapping of RPDO k+1."""
        return self._mapping(pdo.RPDO_MAPPING + k)

    def _mapping(self, index: int) -> tuple[pdo.MappedObject, ...]:
        cached = self._mapping_cache.get(index)
        if cached is not None:
            return cached
        out = []
        for sub in range(1, self.od[(index, 0)].value + 1):
            obj_index, obj_sub, _ = pdo.parse_map_entry(self.od[(index, sub)].value)
            out.append(pdo.MappedObject(obj_index, obj_sub, self.od[(obj_index, obj_sub)].fmt))
        self._mapping_cache[index] = tuple(out)
        return self._mapping_cache[index]

    # ------------------------------------------------------------------ fault injection

    def drop_sdo_replies(self, count: int) -> None:
        """Do not answer the next ``count`` SDO requests."""
        self._drop_sdo += count

    def drop_tpdos(self, count: int) -> None:
        """Swallow the next ``count`` TPDO frames."""
        self._drop_tpdo += count

    def stop_heartbeat(self) -> None:
        self.heartbeat_enabled = False

    def resume_heartbeat(self) -> None:
        self.heartbeat_enabled = True

    async def reboot(self) -> None:
        """Power-cycle: every object back to its power-on value, then boot-up."""
        self.reset_application()
        self.reset_communication_objects()
        await self.boot()

    def disconnect(self) -> None:
        """Fall silent and ignore the bus (the node's cable is pulled)."""
        self.silent = True

    def reconnect(self) -> None:
        self.silent = False

    # ------------------------------------------------------------------ running

    async def run(self) -> None:
        """Boot up and serve the bus until cancelled or the port closes."""
        await self.boot()
        cycle = asyncio.create_task(self._cycle(), name=f"{self.name}-cycle")
        try:
            while True:
                try:
                    msg = await self.port.recv()
                except CanBusError:
                    return
                if not self.silent:
                    await self._dispatch(msg)
        finally:
            cycle.cancel()
            for task in (cycle, *self._tasks):
                task.cancel()
            await asyncio.gather(cycle, *self._tasks, return_exceptions=True)

    async def boot(self) -> None:
        """Send the boot-up message and enter PRE-OPERATIONAL."""
        self.nmt_state = nmt.NmtState.BOOT_UP
        await self.send(nmt.heartbeat_cob_id(self.node_id), nmt.heartbeat_frame(nmt.NmtState.BOOT_UP))
        self.set_nmt_state(nmt.NmtState.PRE_OPERATIONAL, "boot-up")
        self._heartbeat_due = None

    def set_nmt_state(self, state: nmt.NmtState, cause: str) -> None:
        """Enter an NMT state (logged with ``mono_s`` when it changes; event timers restart)."""
        if state is self.nmt_state:
            return
        log.info("sim_node_nmt", node=self.name, old=self.nmt_state.name, new=state.name, cause=cause,
                 mono_s=monotonic_s(), loop_s=asyncio.get_running_loop().time())
        self.nmt_state = state
        self._tpdo_due.clear()

    async def send(self, cob_id: int, data: bytes) -> None:
        if self.silent:
            return
        self.frames_sent += 1
        await self.port.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))

    async def _dispatch(self, msg: can.Message) -> None:
        cob_id, data = msg.arbitration_id, bytes(msg.data)
        if cob_id == nmt.NMT_COB_ID:
            await self._on_nmt(data)
        elif cob_id == nmt.sdo_request_cob_id(self.node_id):
            if self.nmt_state is not nmt.NmtState.STOPPED:
                await self._on_sdo(data)
        elif 0x701 <= cob_id <= 0x77F:
            self._on_heartbeat(cob_id - 0x700, data)
        elif (k := self._rpdo_for(cob_id)) is not None:
            if self.nmt_state is nmt.NmtState.OPERATIONAL:
                await self._on_rpdo(k, data)
        else:
            await self.on_message(cob_id, data)

    async def send_emcy(self, data: bytes) -> None:
        """Send an EMCY frame unless the EMCY COB-ID (0x1014) is marked invalid or the node is
        STOPPED (where only NMT and heartbeat go on)."""
        cob_id = self.od[(0x1014, 0)].value
        if not cob_id & pdo.COB_ID_INVALID and self.nmt_state is not nmt.NmtState.STOPPED:
            await self.send(cob_id & 0x7FF, data)

    def emit_emcy(self, code: int, register: int, vendor: bytes = bytes(5)) -> None:
        """Record an EMCY error in :attr:`emcy_sent` and send it (in a task of the node)."""
        message = emcy.Emcy(code, register, vendor)
        self.emcy_sent.append(message)
        self.spawn(self.send_emcy(emcy.emcy_frame(message)))

    def spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        """Run ``coro`` in a task the node cancels when it stops."""
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _rpdo_for(self, cob_id: int) -> int | None:
        """The RPDO (k for RPDO k+1) valid on ``cob_id``, None if none."""
        for k in range(self.RPDO_COUNT):
            value = self.od[(pdo.RPDO_COMMUNICATION + k, 1)].value
            if not value & pdo.COB_ID_INVALID and value & 0x7FF == cob_id:
                return k
        return None

    async def _on_rpdo(self, k: int, data: bytes) -> None:
        mapping = self.rpdo_mapping(k)
        if len(data) != pdo.pdo_length(mapping):
            self.rpdo_length_errors += 1
            self.emit_emcy(emcy.PDO_LENGTH_ERROR, self.read_object(0x1001, 0) | _COMMUNICATION_REGISTER)
            return
        for obj, value in zip(mapping, pdo.decode_pdo(mapping, data), strict=True):
            try:
                self.receive_write(obj.index, obj.subindex, value, "rpdo")
            except SdoAbortRequest as exc:  # an RPDO has nobody to answer: the value is dropped
                self.rpdo_values_refused += 1
                log.warning("sim_node_rpdo_value_refused", node=self.name, rpdo=k + 1,
                            object=f"0x{obj.index:04X}:{obj.subindex}", value=value, abort=f"0x{exc.code:08X}")

    async def on_message(self, cob_id: int, data: bytes) -> None:
        """Hook: any other frame (RPDO, SYNC...)."""

    async def _on_nmt(self, data: bytes) -> None:
        try:
            command, node = nmt.parse_nmt(data)
        except nmt.NmtFrameError as exc:
            log.warning("nmt_frame_ignored", node=self.name, problem=str(exc))
            return
        if node not in (0, self.node_id):
            return
        if command is nmt.NmtCommand.START:
            self.set_nmt_state(nmt.NmtState.OPERATIONAL, "NMT start")
        elif command is nmt.NmtCommand.STOP:
            self.set_nmt_state(nmt.NmtState.STOPPED, "NMT stop")
        elif command is nmt.NmtCommand.ENTER_PRE_OPERATIONAL:
            self.set_nmt_state(nmt.NmtState.PRE_OPERATIONAL, "NMT enter pre-operational")
        elif command is nmt.NmtCommand.RESET_COMMUNICATION:
            self.reset_communication_objects()
            await self.boot()
        elif command is nmt.NmtCommand.RESET_NODE:
            self.reset_application()
            self.reset_communication_objects()
            await self.boot()

    def reset_application(self) -> None:
        """Hook: application objects back to power-on values (NMT reset node)."""

    def _on_heartbeat(self, node: int, data: bytes) -> None:
        for sub in range(1, self.od[(0x1016, 0)].value + 1):
            producer, time_ms = nmt.parse_consumer_heartbeat(self.od[(0x1016, sub)].value)
            if producer == node and time_ms > 0:
                self._consumer_seen[node] = asyncio.get_running_loop().time()
                if node in self._consumer_lost:  # monitored again (CiA 301)
                    self._consumer_lost.discard(node)
                    log.info("sim_node_heartbeat_resumed", node=self.name, producer=node, mono_s=monotonic_s())

    # ------------------------------------------------------------------ SDO server

    async def _on_sdo(self, data: bytes) -> None:
        if self._drop_sdo > 0:
            self._drop_sdo -= 1
            return
        reply = self.sdo_reply(data)
        if self.sdo_delay_s > 0:
            task = asyncio.create_task(self._late_reply(reply))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
        else:
            await self.send(nmt.sdo_response_cob_id(self.node_id), reply)

    async def _late_reply(self, reply: bytes) -> None:
        await asyncio.sleep(self.sdo_delay_s)
        await self.send(nmt.sdo_response_cob_id(self.node_id), reply)

    def sdo_reply(self, data: bytes) -> bytes:
        """The server's answer to one SDO request frame (expedited transfers only)."""
        try:
            request = sdo.parse_sdo(data, from_client=True)
        except ValueError:
            index, subindex = struct.unpack_from("<HB", data, 1) if len(data) >= 4 else (0, 0)
            return sdo.abort_frame(index, subindex, sdo_aborts.ABORT_COMMAND)
        index, subindex = request.index, request.subindex
        if request.kind is sdo.SdoKind.ABORT:
            return sdo.abort_frame(index, subindex, sdo_aborts.ABORT_COMMAND)
        if not any(key[0] == index for key in self.od):
            return sdo.abort_frame(index, subindex, sdo_aborts.ABORT_NO_OBJECT)
        entry = self.od.get((index, subindex))
        if entry is None:
            return sdo.abort_frame(index, subindex, sdo_aborts.ABORT_NO_SUBINDEX)
        if request.kind is sdo.SdoKind.UPLOAD:
            if not entry.readable:
                return sdo.abort_frame(index, subindex, sdo_aborts.ABORT_WRITE_ONLY)
            raw = struct.pack(entry.fmt, self.read_object(index, subindex))
            return sdo.upload_reply(index, subindex, raw)
        if not request.expedited:
            return sdo.abort_frame(index, subindex, sdo_aborts.ABORT_COMMAND)
        if not entry.writable:
            return sdo.abort_frame(index, subindex, sdo_aborts.ABORT_READ_ONLY)
        payload = request.data if request.size_indicated else request.raw[: entry.size]
        if len(payload) != entry.size:
            return sdo.abort_frame(index, subindex, sdo_aborts.ABORT_LENGTH)
        try:
            self.receive_write(index, subindex, struct.unpack(entry.fmt, payload)[0], "sdo")
        except SdoAbortRequest as exc:
            return sdo.abort_frame(index, subindex, exc.code)
        return sdo.download_reply(index, subindex)

    # ------------------------------------------------------------------ cyclic work

    async def on_tick(self, now: float) -> None:
        """Hook: called every TICK_S (motion, monitoring)."""

    async def on_heartbeat_lost(self, node: int, silent_s: float) -> None:
        """Hook: a consumed heartbeat stayed away longer than its consumer time (after the node's
        EMCY and its 0x1029 reaction)."""

    async def transmit_tpdo(self, k: int) -> None:
        """Send TPDO k+1 now if it is valid, mapped and the node is OPERATIONAL."""
        cob_id = self.od[(pdo.TPDO_COMMUNICATION + k, 1)].value
        mapping = self.tpdo_mapping(k)
        if self.nmt_state is not nmt.NmtState.OPERATIONAL or cob_id & pdo.COB_ID_INVALID or not mapping:
            return
        if self._drop_tpdo > 0:
            self._drop_tpdo -= 1
            return
        values = tuple(self.read_object(m.index, m.subindex) for m in mapping)
        await self.send(cob_id & 0x7FF, pdo.encode_pdo(mapping, values))

    async def transmit_tpdos_with(self, index: int) -> None:
        """Event-driven transmission: every TPDO that maps object ``index`` (its value changed)."""
        for k in range(self.TPDO_COUNT):
            if any(m.index == index for m in self.tpdo_mapping(k)):
                await self.transmit_tpdo(k)

    async def _cycle(self) -> None:
        loop = asyncio.get_running_loop()
        next_tick = loop.time()
        while True:
            now = loop.time()
            if now >= next_tick:
                await self.on_tick(now)
                await self._check_consumers(now)
                next_tick = max(next_tick + self.TICK_S, now)
            dues = [next_tick]
            dues += await self._heartbeat_producer(now)
            dues += await self._tpdo_timers(now)
            await asyncio.sleep(max(0.0, min(dues) - loop.time()))

    async def _heartbeat_producer(self, now: float) -> list[float]:
        period_s = self.od[(0x1017, 0)].value / 1000
        if period_s <= 0:
            self._heartbeat_due = None
            return []
        if self._heartbeat_due is None or self._heartbeat_due > now + period_s:
            self._heartbeat_due = now + period_s
        if now >= self._heartbeat_due:
            if self.heartbeat_enabled:
                await self.send(nmt.heartbeat_cob_id(self.node_id), nmt.heartbeat_frame(self.nmt_state))
            self._heartbeat_due = max(self._heartbeat_due + period_s, now)
        return [self._heartbeat_due]

    async def _tpdo_timers(self, now: float) -> list[float]:
        dues = []
        for k in range(self.TPDO_COUNT):
            period_s = self.od[(pdo.TPDO_COMMUNICATION + k, 5)].value / 1000
            cob_id = self.od[(pdo.TPDO_COMMUNICATION + k, 1)].value
            if period_s <= 0 or cob_id & pdo.COB_ID_INVALID or self.nmt_state is not nmt.NmtState.OPERATIONAL:
                self._tpdo_due.pop(k, None)
                continue
            due, period = self._tpdo_due.get(k, (now + period_s, period_s))
            if period != period_s:
                due = now + period_s
            if now >= due:
                await self.transmit_tpdo(k)
                due = max(due + period_s, now)
            self._tpdo_due[k] = (due, period_s)
            dues.append(due)
        return dues

    async def _check_consumers(self, now: float) -> None:
        for sub in range(1, self.od[(0x1016, 0)].value + 1):
            producer, time_ms = nmt.parse_consumer_heartbeat(self.od[(0x1016, sub)].value)
            seen = self._consumer_seen.get(producer)
            if time_ms == 0 or seen is None:
                continue
            if now - seen > time_ms / 1000:
                # Unmonitored again until the producer's next heartbeat (CiA 301).
                del self._consumer_seen[producer]
                self._consumer_lost.add(producer)
                await self._heartbeat_lost(producer, now - seen)

    async def _heartbeat_lost(self, producer: int, silent_s: float) -> None:
        """CiA 301's heartbeat event: EMCY 0x8130 (sent before 0x1029 may silence it), then the
        error behaviour 0x1029:1, then the profile's reaction (:meth:`on_heartbeat_lost`)."""
        behaviour = nmt.CommunicationErrorBehaviour(self.od[(0x1029, 1)].value)
        log.info("sim_node_heartbeat_lost", node=self.name, producer=producer, silent_s=round(silent_s, 3),
                 error_behaviour=behaviour.name, nmt=self.nmt_state.name, mono_s=monotonic_s(),
                 loop_s=asyncio.get_running_loop().time())
        message = emcy.Emcy(emcy.HEARTBEAT_ERROR, self.read_object(0x1001, 0) | _COMMUNICATION_REGISTER)
        self.emcy_sent.append(message)
        await self.send_emcy(emcy.emcy_frame(message))
        if behaviour is nmt.CommunicationErrorBehaviour.PRE_OPERATIONAL:
            if self.nmt_state is nmt.NmtState.OPERATIONAL:
                self.set_nmt_state(nmt.NmtState.PRE_OPERATIONAL, "heartbeat lost (0x1029:1 = 0)")
        elif behaviour is nmt.CommunicationErrorBehaviour.STOPPED:
            self.set_nmt_state(nmt.NmtState.STOPPED, "heartbeat lost (0x1029:1 = 2)")
        await self.on_heartbeat_lost(producer, silent_s)
