"""How we talk to real instruments: serial drivers implementing the common instrument interface
(``hw.lab.open_lab``), the line-protocol plumbing they share, and twin-backed emulators
(``hw.emulators``). See docs/hardware.md."""
