"""The OpenNI2 backend (``openni`` specs): the driver for live devices and ``.oni`` files
(``driver``) and the native library it runs on (``native``)."""
