"""Everything that carries a registration to its consumers: the OpenIGTLink server and publisher (3D
Slicer, the navigation UI), the DICOM Spatial Registration (REG) object and its export to a PACS.

Enters: registration events from the bus, current state from the store.
Leaves: OpenIGTLink messages on the wire, REG objects to the PACS.
"""
