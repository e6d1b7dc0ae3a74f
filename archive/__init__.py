"""The archive: a scan folder as one DICOM study (``instances.py``), de-identified on request
(``deidentify.py``), sent to the clinic's PACS over C-STORE or DICOMweb STOW-RS (``send.py``), and
the daemon's durable export queue (``queue.py``). Above ``analysis`` (marks, navigation); the
daemon never imports it: ``tbp daemon`` attaches the queue as it attaches the web server.
"""
