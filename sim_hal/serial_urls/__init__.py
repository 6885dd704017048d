"""pyserial URL handlers (`ddrtsim://`, `simavr://`): pyserial looks a scheme up as
`<package>.protocol_<scheme>` in `serial.protocol_handler_packages`, hence the modules' names.
"""
