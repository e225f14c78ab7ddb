"""Detection in a sample stream: static holds (``streaming``: the detector, the stream pairer,
the reference track), the gates that reject a hold (``gates``: settling, saturation, motion), the
sensor noise the detector and gates scale with (``noise``) and its Allan deviation (``allan``).

May import: ``core``.
"""
