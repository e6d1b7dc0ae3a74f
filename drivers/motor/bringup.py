"""What the host writes into the beam drive at bring-up: heartbeats, PDO mapping, safety ramps.

Kept as data plus one coroutine so the configuration can be read (and tested) in one place.
The TPDO mapping follows CiA 301's procedure: invalidate the PDO, clear the mapping count,
write the entries, set the count, set transmission type and event timer, validate the PDO.
"""

from __future__ import annotations

from drivers.motor import cia402, nmt, pdo
from drivers.motor.sdo import SdoClient
from planner.rig import Motor

# TPDO1: one BeamSample per frame. TPDO2: the statusword, for the state machine.
POSITION_TPDO = (
    pdo.MappedObject(cia402.POSITION_ACTUAL, 0, "<i"),
    pdo.MappedObject(cia402.VELOCITY_ACTUAL, 0, "<i"),
)
STATUS_TPDO = (pdo.MappedObject(cia402.STATUSWORD, 0, "<H"),)
QUICK_STOP_STAY = 6  # 0x605A: brake on the quick-stop ramp, stay in QUICK STOP ACTIVE


def event_timer_ms(motor: Motor) -> int:
    """The TPDO event timer for the rig's position rate, ms (at least 1)."""
    return max(1, round(1000 / motor.position_rate_hz))


async def configure(sdo: SdoClient, motor: Motor, host_node_id: int) -> None:
    """Write the drive's heartbeat producer and consumer, TPDO1/TPDO2 and its safety settings."""
    counts = motor.counts_per_degree
    write = sdo.write
    await write(cia402.HEARTBEAT_PRODUCER, 0, "<H", motor.heartbeat_producer_ms)
    consumer = nmt.consumer_heartbeat_value(host_node_id, motor.heartbeat_timeout_ms)
    await write(cia402.HEARTBEAT_CONSUMER, 1, "<I", consumer)
    for k, mapping in enumerate((POSITION_TPDO, STATUS_TPDO)):
        comm, mapping_index = pdo.TPDO_COMMUNICATION + k, pdo.TPDO_MAPPING + k
        cob_id = nmt.tpdo_cob_id(k + 1, motor.node_id)
        await write(comm, 1, "<I", pdo.COB_ID_INVALID | cob_id)
        await write(mapping_index, 0, "<B", 0)
        for sub, obj in enumerate(mapping, start=1):
            await write(mapping_index, sub, "<I", obj.entry)
        await write(mapping_index, 0, "<B", len(mapping))
        await write(comm, 2, "<B", pdo.TRANSMISSION_EVENT_DRIVEN)
        await write(comm, 5, "<H", event_timer_ms(motor))
        await write(comm, 1, "<I", cob_id)
    await write(cia402.FOLLOWING_ERROR_WINDOW, 0, "<I", round(motor.following_error_deg * counts))
    await write(cia402.QUICK_STOP_DECELERATION, 0, "<I", round(motor.max_acceleration_deg_s2 * counts))
    await write(cia402.QUICK_STOP_OPTION, 0, "<h", QUICK_STOP_STAY)
