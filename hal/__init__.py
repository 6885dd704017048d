"""Hardware abstraction: the interface (`hal.base`) and the real drivers."""
