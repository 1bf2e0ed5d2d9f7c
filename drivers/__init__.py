"""I/O with the Stäubli controller: one link interface, one module per protocol; and
:mod:`drivers.dicom_scu`, the pynetdicom SCU association the PACS export and the mock O-arm share.

May import only the standard library, pymodbus, pyserial and pynetdicom (design.md §2).
"""
