"""udev rules for bench adapters (CAN, RS-485, USB drives): the rule files, rendering and a linter."""
