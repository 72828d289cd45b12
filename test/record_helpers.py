"""Helpers shared by the recording tests."""


def read_torn(path):
    """Messages of a file without summary, with mcap's own StreamReader (CRCs checked)."""
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader
    from mcap_ros2.decoder import DecoderFactory
    schemas, channels, out, error = {}, {}, [], None
    decoders = DecoderFactory()
    with open(path, "rb") as f:
        try:
            for rec in StreamReader(f, validate_crcs=True).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message):
                    ch = channels[rec.channel_id]
                    decoded = decoders.decoder_for(ch.message_encoding, schemas[ch.schema_id])(rec.data)
                    out.append((ch.topic, rec.log_time, rec.publish_time, decoded))
        except Exception as err:  # noqa: BLE001 - the torn tail
            error = err
    return out, error
