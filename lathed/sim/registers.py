"""The simulated CNC's Modbus holding-register map (unit id 1).

The default etc/lathed.toml declares the same map for the modbus_cnc
driver; a real controller's map is declared the same way. 32-bit values
take two registers, high word first ("big" word order).
"""
from __future__ import annotations

# name: (address, type, writable, unit)
LATHE_MAP: dict[str, tuple[int, str, bool, str]] = {
    "spindle_rpm_cmd":       (0, "float32", True, "r/min"),
    "spindle_rpm":           (2, "float32", False, "r/min"),
    # writable too: a config can command the speed as an override instead of an S word
    "spindle_override_pct":  (4, "float32", True, "%"),
    "x_mm":                  (6, "float32", False, "mm"),
    "y_mm":                  (8, "float32", False, "mm"),
    "b_deg":                 (10, "float32", False, "deg"),
    "part_count":            (12, "int32", False, ""),
    "cycle_time_s":          (14, "float32", False, "s"),
    "program_state":         (16, "uint16", False, ""),   # 0 idle, 1 running, 2 alarm
    "program_number":        (17, "uint16", False, ""),
    "offset_x_um":           (18, "float32", True, "µm"),
    "depth_of_cut_mm":       (20, "float32", False, "mm"),
    "feed_mm_rev":           (22, "float32", False, "mm/rev"),
    "alarm_code":            (24, "uint16", False, ""),
    "tool_number":           (25, "uint16", False, ""),
    "probe_displacement_um": (26, "float32", False, "µm"),
    "probe_seq":             (28, "uint16", False, ""),
    "spindle_load_pct":      (30, "float32", False, "%"),
    # 1 while the control executes a cutting-feed move (G01/G02/G03, not held): Fanuc's CUT
    # signal; on from the approach in air, before the chip, to the retract
    "cutting_feed":          (32, "uint16", False, ""),
    # 1 while the pass runs at constant surface speed (G96): Fanuc's CSS signal (F2.2)
    "css_active":            (33, "uint16", False, ""),
    # the client's heartbeat count: while an override written by the client is held, the PMC
    # puts it back to 100 % when the count has not changed for HEARTBEAT_TIMEOUT_S (the daemon
    # died or lost the link); armed by the first write
    "heartbeat":             (34, "uint16", True, ""),
    # 1 while a thread is cut, from its cycle's first pass to its last (Fanuc's THRD, F2.3, is
    # on only in the threading blocks: a PMC bit over the whole G76/G92 cycle; rigid tapping
    # likewise): no speed or offset may change in it
    "threading":             (35, "uint16", False, ""),
}
# The control's serial number, ASCII, two characters a register (lathed.modbus_identity): the
# driver reads it at every connect and the daemon commands the control only if it is the
# serial_number of the machine's [identification].
LATHE_IDENTITY = {"serial_number": (36, 8)}
N_REGISTERS = 44
HEARTBEAT_TIMEOUT_S = 1.5   # three of the driver's default 500 ms beats

# The mill (Modbus TCP) and the grinder (Modbus RTU on a pseudo-terminal,
# unit id 1, 115200 8N1) share one map: holding registers, big word order.
CELL_MAP: dict[str, tuple[int, str, bool, str]] = {
    "spindle_rpm_cmd": (0, "float32", True, "r/min"),
    "spindle_rpm":     (2, "float32", False, "r/min"),
    "x_mm":            (4, "float32", False, "mm"),
    "y_mm":            (6, "float32", False, "mm"),
    "z_mm":            (8, "float32", False, "mm"),
    "part_count":      (10, "int32", False, ""),
    "cycle_time_s":    (12, "float32", False, "s"),
    "program_state":   (14, "uint16", False, ""),   # 0 idle, 1 running, 2 alarm
    "program_number":  (15, "uint16", False, ""),
    "alarm_code":      (16, "uint16", False, ""),
}
CELL_IDENTITY = {"serial_number": (20, 8)}
N_CELL_REGISTERS = 28
# what each simulated control says it is
SERIALS = {"lathe": "SIM-LATHE-0001", "mill": "SIM-MILL-0001", "grinder": "SIM-GRINDER-0001"}
