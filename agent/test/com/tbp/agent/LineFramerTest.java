package com.tbp.agent;

import static org.junit.Assert.assertEquals;

import java.nio.charset.StandardCharsets;
import java.util.ArrayList;
import java.util.Arrays;
import java.util.List;
import org.junit.Test;

public class LineFramerTest {

    private final List<String> out = new ArrayList<>();
    private final LineFramer.Sink sink = new LineFramer.Sink() {
        @Override
        public void line(byte[] line) {
            out.add(new String(line, StandardCharsets.UTF_8));
        }

        @Override
        public void overlong(long bytes) {
            out.add("overlong " + bytes);
        }
    };

    private void feed(LineFramer framer, String text) {
        byte[] bytes = text.getBytes(StandardCharsets.UTF_8);
        framer.feed(bytes, 0, bytes.length, sink);
    }

    private static String repeat(char c, int n) {
        char[] chars = new char[n];
        Arrays.fill(chars, c);
        return new String(chars);
    }

    @Test
    public void splitsLinesAcrossFeeds() {
        LineFramer framer = new LineFramer(16);
        feed(framer, "ab");
        feed(framer, "c\nde\n\nf");
        feed(framer, "g\n");
        assertEquals(Arrays.asList("abc\n", "de\n", "\n", "fg\n"), out);
    }

    @Test
    public void aLineOfExactlyTheBoundPassesOneMoreByteIsDropped() {
        LineFramer framer = new LineFramer(16);
        feed(framer, repeat('x', 15) + "\n");
        feed(framer, repeat('y', 16) + "\n" + "ok\n");
        feed(framer, repeat('z', 10));
        feed(framer, repeat('z', 10));
        feed(framer, repeat('z', 1000));
        feed(framer, "\nlast\n");
        assertEquals(Arrays.asList(repeat('x', 15) + "\n", "overlong 17", "ok\n", "overlong 1021", "last\n"), out);
    }

    @Test
    public void megabytesWithoutANewlineAreCountedNotKept() {
        LineFramer framer = new LineFramer(Agent.MAX_LINE);
        byte[] chunk = new byte[1 << 20];
        Arrays.fill(chunk, (byte) 'a');
        for (int i = 0; i < 64; i++) {
            framer.feed(chunk, 0, chunk.length, sink);
        }
        feed(framer, "\n");
        assertEquals(Arrays.asList("overlong " + (64L * (1 << 20) + 1)), out);
    }
}
