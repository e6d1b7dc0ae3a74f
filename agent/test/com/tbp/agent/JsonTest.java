package com.tbp.agent;

import static org.junit.Assert.assertEquals;
import static org.junit.Assert.assertNull;
import static org.junit.Assert.fail;

import java.util.Arrays;
import java.util.LinkedHashMap;
import java.util.Map;
import org.junit.Test;

public class JsonTest {

    @Test
    public void parsesEveryKindOfValue() throws Exception {
        Map<?, ?> object = (Map<?, ?>) Json.parse(
                " {\"i\": -12, \"f\": 2.5e-3, \"s\": \"a\\u00e9\\n\\\"\", \"t\": true, \"n\": null, \"a\": [1, [], {}]}\n");
        assertEquals(-12L, object.get("i"));
        assertEquals(0.0025, object.get("f"));
        assertEquals("a\u00e9\n\"", object.get("s"));
        assertEquals(Boolean.TRUE, object.get("t"));
        assertNull(object.get("n"));
        assertEquals(Arrays.asList(1L, Arrays.asList(), new LinkedHashMap<>()), object.get("a"));
    }

    @Test
    public void integersBeyondALongBecomeDoublesAndTheLastDuplicateWins() throws Exception {
        assertEquals(1e23, Json.parse("100000000000000000000000"));
        assertEquals(9007199254740993L, Json.parse("9007199254740993"));
        assertEquals(2L, ((Map<?, ?>) Json.parse("{\"k\": 1, \"k\": 2}")).get("k"));
        assertEquals(1.0, Json.parse("1.0"));
        assertEquals(0L, Json.parse("-0"));
    }

    @Test
    public void refusesWhatIsNotStrictJson() {
        String[] bad = {"", "{", "{\"a\" 1}", "{'a': 1}", "[1,]", "01", "+1", ".5", "1.", "1e", "NaN", "Infinity",
            "-Infinity", "\"\t\"", "\"\\x\"", "\"\\u12\"", "tru", "{} {}", "nul", "\"abc", "[1 2]", "{\"a\":1,}"};
        for (String text : bad) {
            try {
                Json.parse(text);
                fail("accepted " + text);
            } catch (Json.SyntaxError expected) {
                // refused
            }
        }
    }

    @Test
    public void nestingIsBounded() throws Exception {
        StringBuilder ok = new StringBuilder();
        StringBuilder deep = new StringBuilder();
        for (int i = 0; i < Json.MAX_DEPTH; i++) {
            ok.append('[');
        }
        ok.append('1');
        for (int i = 0; i < Json.MAX_DEPTH; i++) {
            ok.append(']');
        }
        Json.parse(ok.toString());
        try {
            Json.parse("[" + ok + "]");
            fail("accepted " + (Json.MAX_DEPTH + 1) + " nested arrays");
        } catch (Json.SyntaxError expected) {
            assertEquals(true, expected.getMessage().contains("nested deeper"));
        }
        for (int i = 0; i < 100_000; i++) {
            deep.append('[');
        }
        try {
            Json.parse(deep.toString());
            fail("accepted 100000 nested arrays");
        } catch (Json.SyntaxError expected) {
            assertEquals(true, expected.getMessage().contains("nested deeper"));
        }
    }

    @Test
    public void writesWhatItReads() throws Exception {
        Map<String, Object> value = new LinkedHashMap<>();
        value.put("id", 12L);
        value.put("ok", true);
        value.put("x", 0.002);
        value.put("s", "line\nquote\" back\\ \u0001 \ud83d\ude00");
        value.put("nan", Double.NaN);
        value.put("list", Arrays.asList(1L, "two", null));
        String text = Json.write(value);
        assertEquals("{\"id\":12,\"ok\":true,\"x\":0.002,\"s\":\"line\\nquote\\\" back\\\\ \\u0001 \ud83d\ude00\","
                + "\"nan\":null,\"list\":[1,\"two\",null]}", text);
        value.put("nan", null);
        assertEquals(value, Json.parse(text));
        assertEquals("\"\\ud800\"", Json.write("\ud800"));  // a lone surrogate stays encodable
    }
}
