"""Readers and writers of depth recordings, one module per format: depthnav's own
(``recording``, ``recording_writer``), PNG folders (``png_folder``), fakenect folders
(``fakenect``) and OpenNI ``.oni`` files (``oni``)."""
