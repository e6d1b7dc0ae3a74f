package com.tbp.agent;

import java.util.Arrays;

/**
 * Splits one connection's bytes into lines of at most {@code maxLine} bytes (the newline included).
 * A longer line is dropped as it arrives, never buffered whole, and reported once at its newline,
 * so a client that sends megabytes without a newline costs at most {@code maxLine} bytes of memory.
 */
public final class LineFramer {

    /** Receives each complete line (ending in '\n') or the size of each line that was too long. */
    public interface Sink {
        void line(byte[] line);

        void overlong(long bytes);
    }

    private final int maxLine;
    private byte[] buffer = new byte[256];
    private int length;
    private long dropped = -1;  // >= 0 while dropping a line that grew past maxLine

    public LineFramer(int maxLine) {
        this.maxLine = maxLine;
    }

    public void feed(byte[] data, int offset, int count, Sink sink) {
        int end = offset + count;
        int start = offset;
        for (int i = offset; i < end; i++) {
            if (data[i] != '\n') {
                continue;
            }
            int piece = i + 1 - start;
            if (dropped >= 0) {
                long size = dropped + piece;
                dropped = -1;
                sink.overlong(size);
            } else if (length + piece > maxLine) {
                long size = (long) length + piece;
                length = 0;
                sink.overlong(size);
            } else {
                append(data, start, piece);
                byte[] line = Arrays.copyOf(buffer, length);
                length = 0;
                sink.line(line);
            }
            start = i + 1;
        }
        int rest = end - start;
        if (rest == 0) {
            return;
        }
        if (dropped >= 0) {
            dropped += rest;
        } else if (length + rest >= maxLine) {  // even a newline next would make it too long
            dropped = (long) length + rest;
            length = 0;
        } else {
            append(data, start, rest);
        }
    }

    private void append(byte[] data, int start, int count) {
        if (length + count > buffer.length) {
            buffer = Arrays.copyOf(buffer, Math.max(length + count, Math.min(buffer.length * 2, maxLine)));
        }
        System.arraycopy(data, start, buffer, length, count);
        length += count;
    }
}
