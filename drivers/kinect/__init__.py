"""The Kinect 360 backend (``kinect`` specs): the driver (``driver``), the libfreenect binding
(``freenect``), the motor/accelerometer/LED device over pyusb (``motor``) and the accelerometer
axes and units (``axes``)."""
