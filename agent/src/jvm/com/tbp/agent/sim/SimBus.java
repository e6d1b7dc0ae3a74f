package com.tbp.agent.sim;

import java.io.EOFException;
import java.io.IOException;
import java.nio.ByteBuffer;
import java.nio.channels.SocketChannel;

/**
 * The link between the agent under the JVM and the simulated phone that started it
 * (drivers/sim/jvm_agent.py): frames of kind (1 byte), channel (u32), length (u32) and payload,
 * big-endian, over a UNIX socket. The simulator carries the host's agent streams and the camera's
 * answers on it; the agent its answers, camera calls and acknowledgements.
 */
final class SimBus {

    // From the simulator.
    static final int OPEN = 1;
    static final int DATA = 2;
    static final int CLOSE = 3;
    static final int REPLY = 4;
    static final int SYNC = 5;
    // To the simulator.
    static final int LISTEN = 11;
    static final int SENT = 12;
    static final int CLOSED = 13;
    static final int CALL = 14;
    static final int SYNCED = 15;

    static final int MAX_PAYLOAD = 64 << 20;

    /** One frame from the simulator. */
    static final class Frame {
        final int kind;
        final int channel;
        final byte[] payload;

        Frame(int kind, int channel, byte[] payload) {
            this.kind = kind;
            this.channel = channel;
            this.payload = payload;
        }
    }

    // The channel is read and written directly: the streams of Channels.newInputStream and
    // newOutputStream share one lock, so a blocked read would block every write.
    private final SocketChannel socket;
    private final ByteBuffer header = ByteBuffer.allocate(9);

    SimBus(SocketChannel socket) {
        this.socket = socket;
    }

    /** The next frame, or null once the simulator closed the link. Reader thread only. */
    Frame read() throws IOException {
        header.clear();
        if (!fill(header)) {
            return null;
        }
        header.flip();
        int kind = header.get() & 0xff;
        int channel = header.getInt();
        int length = header.getInt();
        if (length < 0 || length > MAX_PAYLOAD) {
            throw new IOException("frame of " + (length & 0xffffffffL) + " bytes from the simulator");
        }
        ByteBuffer payload = ByteBuffer.allocate(length);
        if (!fill(payload)) {
            throw new EOFException("the simulator closed its link within a frame");
        }
        return new Frame(kind, channel, payload.array());
    }

    /** Reads until the buffer is full; false at end of stream before the first byte. */
    private boolean fill(ByteBuffer buffer) throws IOException {
        boolean any = buffer.position() > 0 || !buffer.hasRemaining();
        while (buffer.hasRemaining()) {
            if (socket.read(buffer) < 0) {
                if (!any) {
                    return false;
                }
                throw new EOFException("the simulator closed its link within a frame");
            }
            any = true;
        }
        return true;
    }

    /** Sends one frame; whole frames never interleave. */
    synchronized void write(int kind, int channel, byte[] payload) {
        ByteBuffer frame = ByteBuffer.allocate(9 + payload.length);
        frame.put((byte) kind).putInt(channel).putInt(payload.length).put(payload).flip();
        try {
            while (frame.hasRemaining()) {
                socket.write(frame);
            }
        } catch (IOException e) {
            throw new SimulatorGone(e);
        }
    }

    void close() throws IOException {
        socket.close();
    }

    /** The simulator closed the link while the agent wrote to it. */
    static final class SimulatorGone extends RuntimeException {

        private static final long serialVersionUID = 1L;

        SimulatorGone(IOException cause) {
            super("the simulated phone closed its link: " + cause.getMessage(), cause);
        }
    }
}
