"""Ctrl-C and SIGTERM in the package's command lines: the names of :mod:`sb3_cql.processes`, their home (signals and
child processes), under the module path they have always had."""

from sb3_cql.processes import (
    COMMANDS,
    INTERRUPTED_STATUS,
    INTERRUPTS,
    PR_SET_PDEATHSIG,
    TERMINATED_STATUS,
    die_with_parent,
    exit_status,
    interrupts_blocked,
    interrupts_deferred,
    interrupts_noted,
    keyboard_interrupt,
    quiet_command_startup,
    quiet_startup,
    run_command,
    started,
    terminate_as_interrupt,
)

__all__ = [
    "COMMANDS",
    "INTERRUPTED_STATUS",
    "INTERRUPTS",
    "PR_SET_PDEATHSIG",
    "TERMINATED_STATUS",
    "die_with_parent",
    "exit_status",
    "interrupts_blocked",
    "interrupts_deferred",
    "interrupts_noted",
    "keyboard_interrupt",
    "quiet_command_startup",
    "quiet_startup",
    "run_command",
    "started",
    "terminate_as_interrupt",
]
